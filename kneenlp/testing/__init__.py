"""Test utilities shipped with kneenlp: independent references to check the model against."""
