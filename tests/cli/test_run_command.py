"""The commands' shared exit contract (d3grasp.cli.args.run_command): exit codes and one-line messages."""

from __future__ import annotations

import pytest

from d3grasp.cli.args import run_command


def _raise(exc: BaseException):
    def body() -> None:
        raise exc

    return body


@pytest.mark.parametrize(
    ("exc", "code", "message"),
    [
        (ValueError("bad\n  input"), 2, "prog: error: bad input"),
        (FileNotFoundError("no such file: x.pt"), 2, "prog: error: no such file: x.pt"),
        (KeyboardInterrupt(), 130, "prog: aborted"),
        (KeyboardInterrupt("SIGTERM"), 130, "prog: aborted by SIGTERM"),
    ],
)
def test_errors_exit_with_one_line(capsys, monkeypatch, exc, code, message):
    monkeypatch.delenv("D3GRASP_DEBUG", raising=False)
    assert run_command("prog", _raise(exc), one_line=True) == code
    assert capsys.readouterr().err.strip() == message


def test_body_exit_code_passes_through():
    assert run_command("prog", lambda: None) == 0
    assert run_command("prog", lambda: 3) == 3
