"""The ``threedq`` command (entry point only: it parses the subcommand and hands it to the pipeline).

* ``threedq fit|validate|test|predict --config stages/<stage>.yaml`` — :class:`~threedq.pipeline.lightning_cli.ThreeDQCLI`
  (LightningCLI, subclass mode for model and data, YAML under ``configs/``).
* ``threedq data generate|show|check|import|index`` — :mod:`threedq.pipeline.data_commands`.
* ``threedq em`` — :func:`threedq.pipeline.em.run_em`; ``threedq eval`` — :func:`threedq.pipeline.report.run_eval`.
* ``threedq parse`` — :func:`threedq.pipeline.parse_command.run_parse`; ``threedq label`` — :func:`threedq.pipeline.naming.run_label`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from jsonargparse import ArgumentError, ArgumentParser

from threedq.errors import InputError, error_line
from threedq.pipeline.data_commands import data_parsers, run_data
from threedq.pipeline.em import run_em
from threedq.pipeline.lightning_cli import ThreeDQCLI, explain_parse_error
from threedq.pipeline.naming import run_label
from threedq.pipeline.parse_command import run_parse
from threedq.pipeline.report import run_eval

__all__ = ["build_parser", "main"]

LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")


def build_parser() -> ArgumentParser:
    """The top-level parser (``fit``/``validate``/``test``/``predict`` are handed to :class:`ThreeDQCLI`)."""
    parser = ArgumentParser(prog="threedq", description=__doc__.split("\n\n")[0] if __doc__ else None,
                            exit_on_error=False)  # a parse error is one line (main), not the usage
    sub = parser.add_subcommands(dest="command")
    for name in LIGHTNING_SUBCOMMANDS:
        p = ArgumentParser(description=f"Lightning '{name}' of a stage; see 'threedq {name} --help'.")
        sub.add_subcommand(name, p, help=f"LightningCLI {name} (threedq {name} --config stages/<stage>.yaml)")
    data = ArgumentParser(description="Dataset tools: generate, show, check, import, index.")
    sub.add_subcommand("data", data, help="generate, show, check, import or index a dataset")
    em = ArgumentParser(description=(run_em.__doc__ or "").split("\n")[0])
    em.add_function_arguments(run_em)
    sub.add_subcommand("em", em, help="run the stages in order (view prediction, EM rounds, evaluation)")
    ev = ArgumentParser(description=(run_eval.__doc__ or "").split("\n")[0])
    ev.add_function_arguments(run_eval)
    sub.add_subcommand("eval", ev, help="the paper's tables and figures for a quantizer checkpoint")
    pa = ArgumentParser(description=(run_parse.__doc__ or "").split("\n")[0])
    pa.add_function_arguments(run_parse)
    sub.add_subcommand("parse", pa, help="parse scenes with a trained run: boxes, prototype (C), yaw (R), name")
    la = ArgumentParser(description=(run_label.__doc__ or "").split("\n")[0])
    la.add_function_arguments(run_label)
    sub.add_subcommand("label", la, help="name a few objects (labels.yaml); names propagate to the prototypes")
    data_sub = data.add_subcommands(dest="action")
    for name, p, help_text in data_parsers():
        data_sub.add_subcommand(name, p, help=help_text)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``threedq`` command."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in LIGHTNING_SUBCOMMANDS:
            ThreeDQCLI(args=argv)
            return 0
        cfg = build_parser().parse_args(argv)
        if cfg.command == "data":
            return run_data(cfg.data)
        if cfg.command == "em":
            run_em(**{k: v for k, v in cfg.em.items() if k != "config" or v is not None})
            return 0
        if cfg.command == "eval":
            run_eval(**dict(cfg.eval.items()))
            return 0
        if cfg.command == "parse":
            summary = run_parse(**dict(cfg.parse.items()))
            return 0 if summary["parsed"] or not summary["scenes"] else 1
        if cfg.command == "label":
            run_label(**dict(cfg.label.items()))
            return 0
        build_parser().print_help()
        return 2
    except ArgumentError as e:
        print(f"threedq: error: {explain_parse_error(str(e), argv)}", file=sys.stderr)
        return 2
    except (InputError, OSError, RuntimeError) as e:  # a bad input, a full disk, ...: one line, no traceback
        print(f"threedq: error: {error_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
