import subprocess
import sys

from evseg.cli import main


def test_help_lists_subcommands(capsys):
    assert main([]) == 2
    out = capsys.readouterr().out
    assert "bench" in out and "eval" in out


def test_user_error_is_one_line_and_exit_2(capsys):
    assert main(["bench", "seg", "--repeats", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["evseg bench: error: --repeats must be at least 1, got 0"]


def test_console_script_help_is_fast_and_torch_free():
    code = "import sys; from evseg.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
