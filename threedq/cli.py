"""The ``threedq`` command (entry point only: it parses the subcommand and hands it to the pipeline)."""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

from jsonargparse import ArgumentError, ArgumentParser

from threedq.errors import InputError, error_line

__all__ = ["build_parser", "end_process_group", "main", "one_blas_thread"]

LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")
#: name -> (help, module, function that runs it); a subcommand's module is imported only when its parser is built
_COMMANDS = {
    "data": ("generate, show, check, import or index a dataset", "threedq.pipeline.data_commands", "run_data"),
    "em": ("run the stages in order (view prediction, EM rounds, evaluation)", "threedq.pipeline.em", "run_em"),
    "eval": ("the paper's tables and figures for a quantizer checkpoint", "threedq.pipeline.report", "run_eval"),
    "parse": ("parse scenes with a trained run: boxes, prototype (C), yaw (R), name", "threedq.pipeline.parse_command",
              "run_parse"),
    "label": ("name a few objects (labels.yaml); names propagate to the prototypes", "threedq.pipeline.naming",
              "run_label"),
    "view": ("look at a run in 3D (Rerun): scenes, each round's detections, prototypes, metrics",
             "threedq.pipeline.view", "run_view"),
}  # fmt: skip


def _command_function(name: str) -> Callable[..., Any]:
    """The function that runs subcommand ``name`` (its module imported now)."""
    _, module, function = _COMMANDS[name]
    return getattr(importlib.import_module(module), function)


def build_parser(command: str | None = None) -> ArgumentParser:
    """The top-level parser (``fit``/``validate``/``test``/``predict`` are handed to :class:`ThreeDQCLI`).

    ``command``: build the parser of that subcommand only; ``None`` or a name that is no subcommand: every subcommand
    by name and help line only, without its options and without importing its module.
    """
    description = __doc__.split("\n\n")[0] if __doc__ else None
    parser = ArgumentParser(prog="threedq", description=description, exit_on_error=False)  # a parse error: one line
    sub = parser.add_subcommands(dest="command")
    for name in LIGHTNING_SUBCOMMANDS:
        p = ArgumentParser(description=f"Lightning '{name}' of a stage; see 'threedq {name} --help'.")
        sub.add_subcommand(name, p, help=f"LightningCLI {name} (threedq {name} --config stages/<stage>.yaml)")
    for name, (help_text, _, _) in _COMMANDS.items():
        if command in _COMMANDS and name != command:
            continue
        if command not in _COMMANDS:  # listed only: its options are for 'threedq <name> --help'
            listed = ArgumentParser(description=f"{help_text}; see 'threedq {name} --help'.")
            sub.add_subcommand(name, listed, help=help_text)
        elif name == "data":
            p = ArgumentParser(description="Dataset tools: generate, show, check, import, index.")
            sub.add_subcommand(name, p, help=help_text)
            from threedq.pipeline.data_commands import data_parsers

            actions = p.add_subcommands(dest="action")  # jsonargparse takes them once 'data' is a subcommand
            for action, ap, action_help in data_parsers():
                actions.add_subcommand(action, ap, help=action_help)
        else:
            fn = _command_function(name)
            p = ArgumentParser(description=(fn.__doc__ or "").split("\n")[0])
            p.add_function_arguments(fn)
            sub.add_subcommand(name, p, help=help_text)
    return parser


def one_blas_thread() -> None:
    """Run numpy's and scipy's BLAS on one thread from now on in this process, unless ``OPENBLAS_NUM_THREADS`` is set
    (torch's own threads are untouched)."""
    if os.environ.get("OPENBLAS_NUM_THREADS"):
        return
    os.environ["OPENBLAS_NUM_THREADS"] = "1"  # the BLAS libraries loaded from now on, and child processes (DDP)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")  # those loaded already; the limit stays after the object is gone


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``threedq`` command."""
    argv = list(sys.argv[1:] if argv is None else argv)
    one_blas_thread()
    try:
        if argv and argv[0] in LIGHTNING_SUBCOMMANDS:
            from threedq.pipeline.lightning_cli import ThreeDQCLI

            ThreeDQCLI(args=argv)
            return 0
        command = next((a for a in argv if not a.startswith("-")), None)  # the subcommand, options before it aside
        cfg = build_parser(command).parse_args(argv)
        if cfg.command == "data":
            return _command_function("data")(cfg.data)
        if cfg.command == "em":
            _command_function("em")(**{k: v for k, v in cfg.em.items() if k != "config" or v is not None})
            return 0
        if cfg.command == "parse":
            summary = _command_function("parse")(**dict(cfg.parse.items()))
            return 0 if summary["parsed"] or not summary["scenes"] else 1
        if cfg.command in ("eval", "label", "view"):
            _command_function(cfg.command)(**dict(cfg[cfg.command].items()))
            return 0
        build_parser().print_help()
        return 2
    except ArgumentError as e:
        from threedq.pipeline.lightning_cli import explain_parse_error

        print(f"threedq: error: {explain_parse_error(str(e), argv)}", file=sys.stderr)
        return 2
    except (InputError, OSError, RuntimeError) as e:  # a bad input, a full disk, ...: one line, no traceback
        print(f"threedq: error: {error_line(e)}", file=sys.stderr)
        return 2
    finally:
        end_process_group()


def end_process_group() -> None:
    """Destroy the default process group, if a DDP run formed one in this process (no-op otherwise; no collective).

    Exiting with Lightning's group standing aborts the process at shutdown (gloo's threads, exit -6).
    """
    dist = sys.modules.get("torch.distributed")  # not imported by this process: it formed no group
    if dist is not None and dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


if __name__ == "__main__":
    sys.exit(main())
