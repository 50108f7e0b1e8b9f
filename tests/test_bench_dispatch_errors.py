"""``python -m retinexgs.bench``: a user error raised inside a benchmark is one line and exit code 2."""
import sys
import types

from retinexgs.bench import __main__ as dispatch
from retinexgs.errors import UserError


def test_a_user_error_inside_a_benchmark_is_one_line(monkeypatch, capsys):
    def failing_main(argv):
        raise UserError("the photo is missing")

    monkeypatch.setattr(dispatch, "_load", lambda name: types.SimpleNamespace(main=failing_main))
    monkeypatch.setattr(sys, "argv", ["retinexgs.bench", "darken"])
    assert dispatch._run_from_shell() == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["python -m retinexgs.bench: error: the photo is missing"]
