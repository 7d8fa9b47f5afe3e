"""``python -m kneenlp.cli``."""

import sys

from kneenlp.cli.main import main

sys.exit(main())
