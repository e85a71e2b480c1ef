"""The ``evseg`` console script: one entry point, one module per subcommand.

Each subcommand lives in ``evseg/commands/<name>.py`` and defines ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``. Heavy imports (torch, onnxruntime, cv2)
stay inside ``run`` so that ``evseg --help`` is instant.

User errors (:class:`evseg.errors.EvsegError`) print one line and exit with status 2;
``--debug`` prints the traceback instead. Ctrl-C exits with status 130.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
import traceback

from evseg.errors import EvsegError

# Order in which subcommands are listed in --help: the pipeline's order. Modules found in
# evseg/commands but not listed here follow alphabetically.
ORDER = ["demo", "simulate", "info", "convert", "flow", "segment", "train", "export", "eval", "bench"]


def _command_modules() -> list[str]:
    import evseg.commands as pkg

    found = sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_"))
    return [n for n in ORDER if n in found] + [n for n in found if n not in ORDER]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evseg",
        description="Real-time motion segmentation with event cameras (learned normal flow + graph cuts).",
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    from evseg import __version__

    parser.add_argument("--version", action="version", version=f"evseg {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _command_modules():
        mod = importlib.import_module(f"evseg.commands.{name}")
        p = sub.add_parser(
            name,
            help=mod.HELP,
            description=(mod.__doc__ or mod.HELP).strip(),
            formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        )
        # SUPPRESS: not given after the command, the flag keeps what was given before it.
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show full tracebacks on errors")
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


# Commands whose work is torch on the CPU (training, export) keep OpenMP's default wait policy.
TORCH_COMMANDS = ("train", "export")


def _openmp_waits_passively(command: str) -> None:
    """Make idle OpenMP threads sleep instead of spin, unless the user set a policy.

    OpenMP (numba's threading layer for the normal-flow encoder) keeps its threads spinning for
    a while after each parallel loop, and onnxruntime's threads, which run the network right
    after the encoder, then compete with them for the cores: on 2 cores the network took 5.6
    instead of 3.3 ms for 10 k targets (`evseg bench flow`). torch shares the OpenMP runtime and
    trains faster with spinning threads (a 128-wide head's CPU step: ~6 ms spinning, ~8 ms
    passive), so training and export keep the default. OpenMP reads the policy once, when it
    starts, hence here, before any command imports numba's threads or torch.
    """
    if command not in TORCH_COMMANDS:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


EXTRAS = {"h5py": "formats", "hdf5plugin": "formats", "rosbags": "formats", "aedat": "formats",
          "lightning": "train", "jsonargparse": "train", "onnx": "train", "pytest": "test", "hypothesis": "test"}
"""Top-level module -> the optional dependency group of pyproject.toml that installs it."""


def missing_extra_message(exc: ModuleNotFoundError) -> str | None:
    """What to install for a missing optional dependency, or None for any other missing module
    (a broken install or a bug, reported as an internal error).

    >>> print(missing_extra_message(ModuleNotFoundError("No module named 'h5py'", name="h5py")))
    this needs h5py, part of the optional 'formats' dependencies: pip install "evseg[formats]"
    """
    top = (exc.name or "").split(".")[0]
    if top not in EXTRAS:
        return None
    extra = EXTRAS[top]
    return f"this needs {top}, part of the optional '{extra}' dependencies: pip install \"evseg[{extra}]\""


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    _openmp_waits_passively(args.command)
    try:
        return int(args._run(args) or 0)
    except EvsegError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"evseg {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into e.g. `head`, which closed early: not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print(f"evseg {args.command}: interrupted", file=sys.stderr)
        return 130
    except ModuleNotFoundError as exc:
        message = missing_extra_message(exc)
        if message is None or args.debug:
            return _internal_error(args, exc)
        print(f"evseg {args.command}: error: {message}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug in evseg: say so, keep the traceback one flag away
        return _internal_error(args, exc)


def _internal_error(args, exc: Exception) -> int:
    if args.debug:
        raise exc
    print(
        f"evseg {args.command}: internal error: {type(exc).__name__}: {exc} "
        "(rerun with --debug for the traceback and please report it)",
        file=sys.stderr,
    )
    return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
