import json

import pytest

import kneenlp
from kneenlp.cli import main


def test_simulate_json_and_outputs(tmp_path, capsys):
    code = main(["simulate", "--knee", "synthetic",
                 "--protocol", "set1", "--out", str(tmp_path), "--json", "--noise", "uniform:0.5",
                 "--seed", "4"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert {"trials", "converged", "max_residual", "seconds"} <= set(out)
    assert out["trials"] == out["converged"] == 7 and out["max_residual"] <= 1e-6
    for name in ("kinematics.csv", "measured.csv", "laxity.png", "ligament_forces.png"):
        assert (tmp_path / name).stat().st_size > 0


def test_noise_is_seeded_and_bounded(tmp_path):
    import numpy as np

    from kneenlp import simulate
    from kneenlp.base.conventions import coordinate_columns

    res = simulate(kneenlp.Knee.named("synthetic"), "set1")
    a, b, c = (res.measured("uniform:0.5", seed=s) for s in (1, 1, 2))
    assert a.equals(b) and not a.equals(c)
    err = a[coordinate_columns()].to_numpy() - res.table()[coordinate_columns()].to_numpy()
    assert np.abs(err).max() <= 0.5 and np.abs(err).max() > 0.3


def test_a_signal_inside_a_compiled_kernel_is_still_an_interrupt(monkeypatch, capsys, tmp_path):
    """SIGTERM whose handler raises inside a numba kernel surfaces as SystemError (seen:
    diagnose exited 3, "CPUDispatcher(contact_expansion)"); the exit code is still 143."""
    import os
    import signal
    import time

    from kneenlp.cli.commands import COMMANDS

    def command(args):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        except KeyboardInterrupt:
            raise SystemError("CPUDispatcher(contact_expansion) returned a result with an exception set") from None
        return 0

    monkeypatch.setitem(COMMANDS, "simulate", command)
    code = main(["simulate", "--knee", "synthetic", "--no-plots", "--out", str(tmp_path / "o")])
    assert code == 143 and "terminated (SIGTERM)" in capsys.readouterr().err


def test_a_signal_inside_the_working_set_callback_is_held_and_still_wins(monkeypatch, capfd, tmp_path):
    """SIGINT arriving while Newton takes the working sets (Python): exit 130, one line, no traceback.
    Arriving while CasADi runs the working-set callback (Python called from compiled code: the
    NLP's), it is held there, never raised inside it (CasADi printed the exception's traceback to
    stderr), and raised by the check after.  A signal held past every check still wins when the
    command ends."""
    import os
    import signal

    import numpy as np

    from kneenlp.base.interrupts import Interrupted, catching_signals, check
    from kneenlp.experiment.kneemodel import KneeModel

    original = KneeModel.working_data_batch
    calls = []

    def with_signal(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGINT)
            calls.append("held")  # reached only where the signal is held
        return original(self, *args, **kwargs)

    monkeypatch.setattr(KneeModel, "working_data_batch", with_signal)
    code = main(["simulate", "--knee", "default", "--protocol", "set1", "--no-plots", "--out", str(tmp_path / "o")])
    err = capfd.readouterr().err.strip()
    lines = [line for line in err.splitlines() if not line.startswith("kneenlp: building")]  # a first run's notes
    assert code == 130 and "held" not in calls and lines == ["kneenlp: interrupted (Ctrl-C); finished "
                                                             "work is kept"], err

    model = KneeModel(kneenlp.Knee.default())
    callback = model.working_sets_function(1, order=0)
    calls.clear()
    calls += [1, 1]  # the callback's call is the third
    with catching_signals():
        callback(model.knee.reference_pose[1], model.theta(), np.zeros(1))
        assert "held" in calls
        with pytest.raises(Interrupted):
            check()

    from kneenlp.cli.commands import COMMANDS

    def held_to_the_end(args):
        from kneenlp.base.interrupts import held

        with held():
            os.kill(os.getpid(), signal.SIGTERM)
        return 0

    monkeypatch.setitem(COMMANDS, "simulate", held_to_the_end)
    assert main(["simulate", "--knee", "synthetic", "--no-plots", "--out", str(tmp_path / "p")]) == 143


def test_the_command_line_starts_without_the_heavy_imports():
    """``kneenlp --help`` and argument errors load neither CasADi, SciPy, pandas nor numba (the
    commands import them where they need them), and ``kneenlp.Knee`` still resolves on first use."""
    import subprocess
    import sys

    code = ("import sys; from kneenlp.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "main(['identify', '--starts', '0'])\n"
            "heavy = [m for m in ('casadi', 'scipy', 'pandas', 'numba', 'matplotlib') if m in sys.modules]\n"
            "import kneenlp\nprint(heavy, kneenlp.Knee.__name__)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.stdout.strip().splitlines()[-1] == "[] Knee", (run.stdout, run.stderr)
    assert "--starts" in run.stderr and "Traceback" not in run.stderr
    assert "ParameterSet" in dir(kneenlp)
    with pytest.raises(AttributeError, match="no attribute 'Kne'"):
        kneenlp.Kne  # noqa: B018


def test_a_signal_in_the_first_instant_is_one_line():
    """SIGINT or SIGTERM while the command is still starting (imports included): 130/143 and one
    line, never a traceback."""
    import signal
    import subprocess
    import sys
    import time

    for sig, status in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        for delay in (0.3, 0.6, 1.0):
            proc = subprocess.Popen([sys.executable, "-m", "kneenlp.cli", "simulate", "--knee", "default",
                                     "--protocol", "set3"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                    text=True)
            time.sleep(delay)
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=120)
            if proc.returncode == 0:
                continue
            assert proc.returncode == status, (delay, proc.returncode, err)
            assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


def test_modes_are_listed_once_for_the_library_and_the_command_line(capsys):
    """Every mode is a Literal type: the parser's choices are its names, the library refuses any
    other value in the one-line "unknown X; known: ..." form, and ``--knee``'s help lists the
    knees the package ships (a knee added to the resources is listed without an edit)."""
    import typing

    from kneenlp.base import modes
    from kneenlp.base.errors import InputError
    from kneenlp.base.resources import shipped_knees
    from kneenlp.cli.parser import build_parser
    from kneenlp.estimation.identify import identify

    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and "identify" in a.choices).choices
    actions = {a.dest: a for a in sub["identify"]._actions}
    assert tuple(actions["method"].choices) == typing.get_args(modes.Method)
    assert tuple(actions["strategy"].choices) == typing.get_args(modes.Strategy)
    assert all(name in actions["knee"].help for name in shipped_knees()) and "s192803" in shipped_knees()
    with pytest.raises(InputError, match=r"unknown method 'complex'; known: nested, simultaneous"):
        identify(kneenlp.Knee.named("synthetic"), "unused.csv", method="complex")
    with pytest.raises(InputError, match=r"--format: unknown export format 'mps'; known: c, casadi, nl"):
        modes.checked("export format", "mps", modes.ExportFormat, field="--format")
