"""The ``threedq`` command.

* ``threedq fit|validate|test|predict --config stages/<stage>.yaml`` — a :class:`ThreeDQCLI`
  (LightningCLI, subclass mode for model and data, YAML under ``configs/``).
* ``threedq data generate|show|check`` — the embedded dataset generator, its contact sheet and a
  validator for any dataset folder.

A ``--config`` path that does not exist relative to the working directory is looked up in the
packaged ``configs/`` folder, so ``threedq fit --config stages/viewpred.yaml`` works anywhere.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import lightning as L
from jsonargparse import ArgumentParser
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

from threedq.scene import SceneValidationError

__all__ = ["ThreeDQCLI", "main", "resolve_config", "packaged_configs_dir"]

LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")


def packaged_configs_dir() -> Path:
    """The folder of configs shipped with threedq (source checkout or installed package)."""
    package = Path(__file__).resolve().parent
    source_tree = package.parent / "configs"  # a source checkout or an editable install
    if source_tree.is_dir() and (package.parent / "pyproject.toml").is_file():
        return source_tree
    return package / "configs"  # an installed wheel: configs/ is shipped as threedq/configs/


def resolve_config(path: str | Path) -> Path:
    """``path`` if it exists, else the same relative path inside the packaged configs folder.

    Raises:
        FileNotFoundError: naming both places that were tried.
    """
    p = Path(path).expanduser()
    if p.is_file():
        return p
    packaged = packaged_configs_dir() / p
    if not p.is_absolute() and packaged.is_file():
        return packaged
    raise FileNotFoundError(f"config {str(path)!r} not found (tried {p.resolve()} and {packaged})")


def _resolve_config_args(argv: Sequence[str]) -> list[str]:
    out: list[str] = []
    it = iter(argv)
    for a in it:
        if a == "--config":
            out += [a, str(resolve_config(next(it, "")))]
        elif a.startswith("--config="):
            out.append("--config=" + str(resolve_config(a.split("=", 1)[1])))
        else:
            out.append(a)
    return out


class ThreeDQCLI(LightningCLI):
    """LightningCLI for every threedq stage: any LightningModule / LightningDataModule via ``class_path``.

    Each run saves its resolved ``config.yaml`` in the log directory (overwriting a previous one of the
    same directory, so that a resumed run can be restarted from it).
    """

    def __init__(
        self,
        args: Sequence[str] | None = None,
        run: bool = True,
        model_setup: Callable[[L.LightningModule], None] | None = None,
    ) -> None:
        """Parse ``args`` (default: the command line), instantiate, and with ``run`` run the subcommand.

        ``model_setup`` is called with the instantiated model before anything runs (``threedq em`` uses it
        to hand every stage the same :class:`~threedq.crop_cache.CropCache`).
        """
        self._model_setup = model_setup
        with warnings.catch_warnings():
            # threedq passes its own (config-resolved) command line as args= on purpose.
            warnings.filterwarnings("ignore", message=".*args parameter is intended to run from within Python.*")
            self._init(args, run)

    def _init(self, args: Sequence[str] | None, run: bool) -> None:
        super().__init__(
            model_class=L.LightningModule,
            datamodule_class=L.LightningDataModule,
            subclass_mode_model=True,
            subclass_mode_data=True,
            save_config_kwargs={"overwrite": True},
            seed_everything_default=0,
            parser_kwargs={"default_env": True},
            args=list(args) if args is not None else None,
            run=run,
        )

    def instantiate_classes(self) -> None:
        super().instantiate_classes()
        if self._model_setup is not None:
            self._model_setup(self.model)

    def instantiate_trainer(self, **kwargs: Any) -> L.Trainer:
        """Give every run a self-contained folder ``trainer.default_root_dir``.

        Unless the config names its own, the loggers are TensorBoard + CSV writing straight into that
        folder (beside the saved ``config.yaml``), and a ModelCheckpoint keeps ``checkpoints/last.ckpt``
        there, refreshed every 100 training steps, so that ``--ckpt_path <root>/checkpoints/last.ckpt`` resumes a killed run.
        """
        cfg = self._get(self.config_init, "trainer", default={})
        root = Path(cfg.get("default_root_dir") or "runs/default")
        if cfg.get("logger") in (None, True) and not cfg.get("fast_dev_run"):
            kwargs["logger"] = [
                TensorBoardLogger(save_dir=str(root), name="", version=""),
                CSVLogger(save_dir=str(root), name="", version=""),
            ]
        callbacks = list(cfg.get("callbacks") or [])
        if cfg.get("enable_checkpointing") is not False and not any(isinstance(c, ModelCheckpoint) for c in callbacks):
            ckpt = ModelCheckpoint(dirpath=root / "checkpoints", save_last=True, every_n_train_steps=100)
            kwargs["callbacks"] = [*callbacks, ckpt]
        return super().instantiate_trainer(**kwargs)


def _data_parsers() -> list[tuple[str, ArgumentParser, str]]:
    gen = ArgumentParser(description="Generate the embedded CLEVR-veggie-like dataset (offline, deterministic, resumable).")
    gen.add_argument("--out", required=True, help="output dataset folder")
    gen.add_argument("--scenes", type=int, default=300, help="number of scenes over all generated splits")
    gen.add_argument("--seed", type=int, default=0, help="seed of the train/val scenes")
    gen.add_argument("--test_seed", type=int | None, default=None, help="seed of the test scenes (default: derived from --seed)")
    gen.add_argument("--split", type=list[str], default=["train", "val", "test"], help="splits to generate")
    gen.add_argument("--split_fractions", type=tuple[float, float, float], default=(0.8, 0.1, 0.1))
    gen.add_argument("--image_size", type=tuple[int, int], default=(128, 128), help="[H, W] in pixels")
    gen.add_argument("--views", type=int, default=28, help="cameras per scene")
    gen.add_argument("--min_objects", type=int, default=1)
    gen.add_argument("--max_objects", type=int, default=3)
    gen.add_argument("--categories", type=list[str] | None, default=None, help="category names to use (default all 41)")
    gen.add_argument("--workers", type=int, default=2, help="rendering processes")
    gen.add_argument("--progress", type=bool, default=True)

    show = ArgumentParser(description="Draw a contact sheet (rgb, depth, instances, GT boxes) of a dataset.")
    show.add_argument("dir", help="dataset folder")
    show.add_argument("--out", required=True, help="PNG to write")
    show.add_argument("--scenes", type=int, default=4)
    show.add_argument("--split", type=str | None, default=None)

    check = ArgumentParser(description="Validate every scene of a dataset folder; one line per bad file.")
    check.add_argument("dir", help="dataset folder")

    return [
        ("generate", gen, "generate the embedded dataset"),
        ("show", show, "draw a contact sheet PNG"),
        ("check", check, "validate a dataset folder"),
    ]


def build_parser() -> ArgumentParser:
    """The top-level parser (``fit``/``validate``/``test``/``predict`` are handed to :class:`ThreeDQCLI`)."""
    parser = ArgumentParser(prog="threedq", description=__doc__.split("\n\n")[0] if __doc__ else None)
    sub = parser.add_subcommands(dest="command")
    for name in LIGHTNING_SUBCOMMANDS:
        p = ArgumentParser(description=f"Lightning '{name}' of a stage; see 'threedq {name} --help'.")
        sub.add_subcommand(name, p, help=f"LightningCLI {name} (threedq {name} --config stages/<stage>.yaml)")
    data = ArgumentParser(description="Dataset tools: generate, show, check.")
    sub.add_subcommand("data", data, help="generate, show or check a dataset")
    from threedq.em import run_em

    em = ArgumentParser(description=(run_em.__doc__ or "").split("\n")[0])
    em.add_function_arguments(run_em)
    sub.add_subcommand("em", em, help="run the stages in order (view prediction, EM rounds, evaluation)")
    from threedq.report import run_eval

    ev = ArgumentParser(description=(run_eval.__doc__ or "").split("\n")[0])
    ev.add_function_arguments(run_eval)
    sub.add_subcommand("eval", ev, help="the paper's tables and figures for a quantizer checkpoint")
    data_sub = data.add_subcommands(dest="action")
    for name, p, help_text in _data_parsers():
        data_sub.add_subcommand(name, p, help=help_text)
    return parser


def _run_data(cfg) -> int:  # noqa: ANN001 - jsonargparse Namespace
    action = cfg.action
    args = cfg[action]
    if action == "generate":
        from threedq.data.generate import GeneratorConfig, generate_dataset

        config = GeneratorConfig(
            image_size=tuple(args.image_size),
            num_views=args.views,
            min_objects=args.min_objects,
            max_objects=args.max_objects,
            categories=tuple(args.categories) if args.categories else None,
        )
        index = generate_dataset(
            args.out,
            num_scenes=args.scenes,
            seed=args.seed,
            config=config,
            split_fractions=tuple(args.split_fractions),
            test_seed=args.test_seed,
            splits=tuple(args.split),
            workers=args.workers,
            progress=args.progress,
        )
        counts = {s: len(index.files(s)) for s in ("train", "val", "test")}
        print(f"wrote {sum(counts.values())} scenes to {args.out} ({', '.join(f'{k} {v}' for k, v in counts.items())})")
        return 0
    if action == "show":
        from threedq.data.show import contact_sheet

        out = contact_sheet(args.dir, args.out, num_scenes=args.scenes, split=args.split)
        print(f"wrote {out}")
        return 0
    if action == "check":
        return check_dataset(args.dir)
    raise AssertionError(action)


def check_dataset(folder: str | Path) -> int:
    """Validate ``folder/index.json`` and every scene it lists; print one line per bad file. Returns 0 if all good."""
    from threedq.scene import load_index, load_scene

    index = load_index(folder)
    bad = 0
    for entry in index.scenes:
        try:
            load_scene(Path(folder) / entry["file"], bounds=index.scene_bounds, num_categories=len(index.categories))
        except SceneValidationError as e:
            print(e)
            bad += 1
    n = len(index.scenes)
    print(f"{n - bad}/{n} scenes valid in {folder}")
    return 1 if bad else 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``threedq`` command."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in LIGHTNING_SUBCOMMANDS:
            ThreeDQCLI(args=_resolve_config_args(argv))
            return 0
        cfg = build_parser().parse_args(argv)
        if cfg.command == "data":
            return _run_data(cfg.data)
        if cfg.command == "em":
            from threedq.em import run_em

            run_em(**{k: v for k, v in cfg.em.items() if k != "config" or v is not None})
            return 0
        if cfg.command == "eval":
            from threedq.report import run_eval

            run_eval(**dict(cfg.eval.items()))
            return 0
        build_parser().print_help()
        return 2
    except (SceneValidationError, FileNotFoundError, RuntimeError) as e:
        print(f"threedq: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
