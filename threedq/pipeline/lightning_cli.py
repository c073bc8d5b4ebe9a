"""LightningCLI for every threedq stage, and where configs are found.

A ``--config`` path missing relative to the working directory is looked up in the packaged ``configs/`` folder. Every
fault of a config, a pre-0.2 class path or a bad ``--ckpt_path`` is one line naming the config file (or the command
line) and the field (:class:`ConfigError`, :class:`OldClassPathError`).
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Optional

import lightning as L
import torch
import yaml
from jsonargparse import ArgumentError
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

from threedq.errors import InputError, flatten_message, user_error_in_chain
from threedq.locks import hold_folder
from threedq.pipeline.precision import cpu_precision
from threedq.pipeline.strategy import DDPStrategy
from threedq.stages.checkpoint import AtomicCheckpointIO, LastStepCheckpoint, checkpoint_stage

__all__ = ["DEFAULT_DATA_CONFIG", "ThreeDQCLI", "ConfigError", "OldClassPathError", "dataset_num_classes",
           "dataset_symmetry_order", "default_data", "packaged_configs_dir", "config_chain", "expand_configs",
           "load_config", "resolve_config", "resolve_config_args", "test_checkpoint"]

LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")
#: Where a run writes when its config names no ``trainer.default_root_dir``.
DEFAULT_ROOT = "runs/default"
#: The dataset of a run whose configs name none (a stage config says how it loads data, a data config which data).
DEFAULT_DATA_CONFIG = "data/clevr_veggie.yaml"


def default_data() -> dict[str, Any]:
    """The ``data`` block of :data:`DEFAULT_DATA_CONFIG` (``class_path`` and ``init_args``)."""
    return yaml.safe_load(resolve_config(DEFAULT_DATA_CONFIG).read_text(encoding="utf-8"))["data"]


def packaged_configs_dir() -> Path:
    """The folder of configs shipped with threedq (source checkout or installed package)."""
    package = Path(__file__).resolve().parents[1]
    source_tree = package.parent / "configs"
    if source_tree.is_dir() and (package.parent / "pyproject.toml").is_file():
        return source_tree
    return package / "configs"


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
    if p.is_absolute():
        raise FileNotFoundError(f"config {str(path)!r} not found")
    raise FileNotFoundError(f"config {str(path)!r} not found (tried {p.resolve()} and {packaged})")


#: Stage arguments the CLI links from the DataModule (``link_arguments``): a config does not set them.
LINKED_FROM_DATA = ("num_classes", "symmetry_order")


def _refuse_linked(args: Sequence[str]) -> None:
    """Refuse a config file or command line that sets a :data:`LINKED_FROM_DATA` argument to a value (not ``null``).

    Raises:
        ConfigError: naming the file (or the command line) and the field.
    """
    for where, what in _sources(args):
        if where == "command line":
            continue
        init = ((what or {}).get("model") or {}).get("init_args") if isinstance(what, dict) else None
        for key in LINKED_FROM_DATA:
            if isinstance(init, dict) and init.get(key) is not None:
                raise ConfigError(f"{where}: field 'model.init_args.{key}': taken from the dataset's index.json "
                                  "(linked from the data); remove it, or use a dataset with those categories")
    prev = ""
    for a in args:
        key, _, value = a.partition("=") if a.startswith("--") else (prev, "", a)
        name = key.removeprefix("--model.init_args.").removeprefix("--model.")
        if name in LINKED_FROM_DATA and key.startswith("--model.") and value not in ("", "null", "None"):
            raise ConfigError(f"--{key.lstrip('-')}: taken from the dataset's index.json (linked from the data); "
                              "remove it, or use a dataset with those categories")
        prev = a if a.startswith("--") and "=" not in a else ""


def _dataset_value(datamodule: Any, name: str) -> Any:
    """``datamodule.<name>`` (``num_classes``, ``symmetry_order``), or None for a DataModule that does not say; data
    whose ``index.json`` is not there yet is made first (``prepare_data``)."""
    if not hasattr(type(datamodule), name) and name not in vars(datamodule):
        return None
    try:
        return getattr(datamodule, name)
    except InputError:
        prepare = getattr(datamodule, "prepare_data", None)
        if not callable(prepare):
            raise
        prepare()
        return getattr(datamodule, name)


def dataset_num_classes(datamodule: Any) -> int | None:
    """The DataModule's category count (a scene folder's ``index.json``), linked to a stage's ``num_classes``."""
    n = _dataset_value(datamodule, "num_classes")
    return None if n is None else int(n)


def dataset_symmetry_order(datamodule: Any) -> list[int] | None:
    """Per category, its yaw symmetry order (a scene folder's ``index.json``), linked to ``symmetry_order``."""
    sym = _dataset_value(datamodule, "symmetry_order")
    return None if sym is None else [int(o) for o in sym]


class OldClassPathError(InputError):
    """A config or command line names a stage or DataModule by its pre-0.2 top-level path."""


class ConfigError(InputError):
    """A config file (or the command line) does not parse, or names an unknown key or a value of the wrong type."""


def check_config_file(path: Path) -> None:
    """Refuse a config that is not YAML or not a mapping, and pre-0.2 class paths in it (one line naming ``path``).

    Raises:
        ConfigError, OldClassPathError.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, IsADirectoryError) as e:
        raise ConfigError(f"{path}: field '<file>': not a YAML text file ({type(e).__name__})") from e
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or flatten_message(str(e))
        raise ConfigError(f"{path}: field '<file>': not valid YAML{where}: {problem}") from e
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{path}: field '<file>': expected a mapping of keys (model, data, trainer, ...), "
                          f"got a {type(data).__name__}")
    check_class_paths(text, str(path))


def _has_key(tree: Any, keys: list[str]) -> bool:
    for k in keys:
        if not isinstance(tree, dict) or k not in tree:
            return False
        tree = tree[k]
    return True


def _find_key(tree: Any, name: str, prefix: str = "") -> str | None:
    """The dotted path of the first key ``name`` anywhere in ``tree`` (depth-first), or None."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            here = f"{prefix}{k}"
            if k == name:
                return here
            found = _find_key(v, name, here + ".")
            if found:
                return found
    return None


def _sources(args: Sequence[str]) -> list[tuple[str, Any]]:
    """What each ``--config`` file (its YAML tree) and each command-line ``--key`` sets, in order."""
    out: list[tuple[str, Any]] = []
    prev = ""
    for a in args:
        if prev == "--config" or a.startswith("--config="):
            path = Path(a.split("=", 1)[1] if a.startswith("--config=") else a)
            try:
                out.append((str(path), yaml.safe_load(path.read_text(encoding="utf-8"))))
            except (OSError, UnicodeDecodeError, yaml.YAMLError):
                pass
        elif a.startswith("--") and a != "--config":
            out.append(("command line", a[2:].split("=", 1)[0]))
        prev = a
    return out


def explain_parse_error(message: str, args: Sequence[str]) -> str:
    """One line for a jsonargparse error: where the faulty field is set (the last source that sets it), the field,
    and what is wrong."""
    text = flatten_message(message)
    key = None
    m = re.match(r'Parser key "([^"]+)": ?(.*)$', text)
    if m:
        key, text = m.group(1), m.group(2)
    text = re.sub(r"^- ", "", text)
    m2 = re.search(r"(?:does not accept option|Option) '([^']+)'", text)
    nested = m2.group(1).lstrip("-") if m2 else None
    for where, what in reversed(_sources(args)):
        if where == "command line":
            if what == key or (nested is not None and what.split(".")[-1] == nested.split(".")[-1]):
                return f"--{what}: {text}"
            continue
        if nested is not None:
            top = key.split(".")[0] if key else None
            base = what.get(top) if top and isinstance(what, dict) else what
            found = _find_key(base, nested.split(".")[-1]) if isinstance(base, dict) else None
            if found is not None:
                return f"{where}: field '{top + '.' + found if top else found}': {text}"
        elif key is not None and _has_key(what, key.split(".")):
            return f"{where}: field '{key}': {text}"
    field = nested or key
    return f"--{field}: {text}" if field else f"command line: {text}"


_OLD_CLASS_PATH = re.compile(r"((?:stages|datamodules)\.[A-Za-z_][\w.]*)$")

#: modules renamed so that each data module is named as its format's reader (:mod:`threedq.data.formats`)
RENAMED_MODULES = {"threedq.datamodules.tum_rgbd": "threedq.datamodules.tum",
                   "threedq.datamodules.kinect_open3d": "threedq.datamodules.open3d",
                   "threedq.datamodules.camera_rig": "threedq.datamodules.rig"}


def _refuse_old(value: str, where: str) -> None:
    path = value.strip().strip("'\"")
    m = _OLD_CLASS_PATH.match(path)
    if m:
        old = m.group(1)
        raise OldClassPathError(f"{where}: field 'class_path': '{old}' is the path before threedq 0.2; use "
                                f"'threedq.{old}'")
    module, _, name = path.rpartition(".")
    if module in RENAMED_MODULES:
        raise OldClassPathError(f"{where}: field 'class_path': '{path}' was renamed; use "
                                f"'{RENAMED_MODULES[module]}.{name}'")


def check_class_paths(yaml_text: str, where: str) -> None:
    """Refuse ``stages.X`` / ``datamodules.X`` in the ``class_path`` entries of a YAML config.

    Raises:
        OldClassPathError: one line naming ``where``, the old path and the new one.
    """
    for line in yaml_text.splitlines():
        key, sep, value = line.split("#", 1)[0].partition(":")
        if sep and key.strip().lstrip("- ") == "class_path":
            _refuse_old(value, where)


def _is_class_key(key: str) -> bool:
    return key in ("--model", "--data") or key.endswith(".class_path")


def config_chain(path: str | Path) -> list[Path]:
    """The config files that ``path`` stands for, base first: a top-level ``base:`` key names the config it changes (a
    path relative to its own folder, else to the packaged configs), which may have a base in turn.

    Raises:
        ConfigError: a ``base`` that is not a path, or a chain that comes back to a config it holds.
    """
    chain: list[Path] = []
    p = resolve_config(path)
    while True:
        check_config_file(p)
        if p.resolve() in (c.resolve() for c in chain):
            raise ConfigError(f"{p}: field 'base': the configs' bases form a loop")
        chain.insert(0, p)
        doc = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
        base = doc.get("base")
        if base is None:
            return chain
        if not isinstance(base, str) or not base:
            raise ConfigError(f"{p}: field 'base': expected the path of the config this one changes, got {base!r}")
        sibling = p.parent / base
        p = sibling if sibling.is_file() else resolve_config(base)


def load_config(path: str | Path) -> dict[str, Any]:
    """The config ``path`` as it runs: its bases' keys with its own on top, mapping by mapping (``base`` dropped)."""

    def merge(under: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
        out = dict(under)
        for k, v in over.items():
            out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
        return out

    doc: dict[str, Any] = {}
    for p in config_chain(path):
        doc = merge(doc, yaml.safe_load(p.read_text(encoding="utf-8")) or {})
    doc.pop("base", None)
    return doc


def expand_configs(paths: Sequence[str | Path]) -> list[Path]:
    """Every config of ``paths`` with its bases before it (:func:`config_chain`), in order."""
    return [c for p in paths for c in config_chain(p)]


def resolve_config_args(argv: Sequence[str]) -> list[str]:
    """``argv`` with every ``--config`` resolved (:func:`resolve_config`), preceded by its bases (:func:`config_chain`),
    and every class path checked."""
    out: list[str] = []
    prev = ""
    for a in argv:
        if prev == "--config":
            *bases, path = config_chain(a)
            for b in bases:
                out += [str(b), "--config"]
            a = str(path)
        elif a.startswith("--config="):
            *bases, path = config_chain(a.split("=", 1)[1])
            out += [f"--config={b}" for b in bases]
            a = "--config=" + str(path)
        elif _is_class_key(prev):
            _refuse_old(a, f"command line {prev}")
        elif a.startswith("--") and "=" in a and _is_class_key(a.split("=", 1)[0]):
            _refuse_old(a.split("=", 1)[1], f"command line {a.split('=', 1)[0]}")
        out.append(a)
        prev = a if a.startswith("--") else ""
    if prev == "--config":
        raise FileNotFoundError("--config: expected a path after it")
    return out


def _runs_on_cpu(trainer: Any) -> bool:
    """Whether a trainer config (``accelerator``: ``cpu``, or ``auto`` on a machine without CUDA) trains on the CPU."""
    accelerator = str(trainer.get("accelerator") or "auto")
    return accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available())


class ThreeDQCLI(LightningCLI):
    """LightningCLI for every threedq stage: any LightningModule / LightningDataModule via ``class_path``.

    Each run saves its resolved ``config.yaml`` in the log directory (overwriting one there). A stage config's ``data``
    block holds how the stage loads a dataset (no ``class_path``), a data config (``configs/data/*.yaml``) which
    dataset; the default is :data:`DEFAULT_DATA_CONFIG`'s.
    """

    def add_arguments_to_parser(self, parser: Any) -> None:
        """The default dataset, and the stage arguments linked from the DataModule (:data:`LINKED_FROM_DATA`)."""
        parser.set_defaults({"data": default_data()})
        parser.add_argument("--presets", type=Optional[dict[str, str]], default=None,
                            help="a data config's stage presets (read by threedq em; see threedq.pipeline.presets)")
        parser.add_argument("--base", type=Optional[str], default=None,
                            help="the config a config file changes (read before it; see threedq.pipeline.lightning_cli."
                                 "config_chain)")
        for key, compute in zip(LINKED_FROM_DATA, (dataset_num_classes, dataset_symmetry_order)):
            parser.link_arguments("data", f"model.init_args.{key}", compute_fn=compute, apply_on="instantiate")

    def __init__(self, args: Sequence[str] | None = None, run: bool = True,
                 model_setup: Callable[[L.LightningModule], None] | None = None) -> None:
        """Parse ``args`` (default: the command line), instantiate, and with ``run`` run the subcommand.

        ``model_setup`` is called with the instantiated model before anything runs.
        """
        self._model_setup = model_setup
        self._hold = ExitStack()
        with self._hold, warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*args parameter is intended to run from within Python.*")
            self._init(None if args is None else resolve_config_args(args), run)

    def _init(self, args: Sequence[str] | None, run: bool) -> None:
        self._args = list(args or [])
        super().__init__(model_class=L.LightningModule, datamodule_class=L.LightningDataModule,
                         subclass_mode_model=True, subclass_mode_data=True, save_config_kwargs={"overwrite": True},
                         seed_everything_default=0,
                         parser_kwargs={"default_env": True, "exit_on_error": False},
                         args=list(args) if args is not None else None, run=run)

    def subcommands(self) -> dict[str, set[str]]:  # type: ignore[override]  # Lightning's is a staticmethod
        """Lightning's subcommands and the trainer arguments each skips; only the one the command line starts with."""
        every = LightningCLI.subcommands()
        first = self._args[0] if self._args else None
        return {first: every[first]} if first in every else every

    def parse_arguments(self, parser: Any, args: Any) -> None:
        """Parse; a fault is a :class:`ConfigError` naming the config file that sets the field (or the command line), a
        ``--ckpt_path`` that cannot be loaded safely or that another stage wrote an :class:`InputError`."""
        _refuse_linked(self._args)
        try:
            super().parse_arguments(parser, args)
        except ArgumentError as e:
            raise ConfigError(explain_parse_error(str(e), self._args)) from None
        sub = self.config.get(self.config.get("subcommand") or "") or self.config
        ckpt = sub.get("ckpt_path") if hasattr(sub, "get") else None
        if not ckpt or ckpt in ("last", "best", "hpc", "registry"):
            return
        if not Path(ckpt).is_file():
            raise InputError(f"--ckpt_path {ckpt}: no such file")
        stage = checkpoint_stage(ckpt)
        model = sub.get("model")
        cls = model.get("class_path") if hasattr(model, "get") else None
        wanted = cls.split(".")[2] if isinstance(cls, str) and cls.startswith("threedq.stages.") else None
        if stage and wanted and stage != wanted:
            raise InputError(f"{ckpt}: this is a {stage} checkpoint; --ckpt_path of {cls} needs a {wanted} "
                             "checkpoint")

    def _parse_ckpt_path(self) -> None:
        """After Lightning puts ``--ckpt_path``'s saved hyperparameters over the config, a named start file that is not
        there (``encoder_ckpt``, ``bank_ckpt``: replaced by the checkpoint; ``detector_ckpt``, ``init_bank_ckpt``:
        dropped) is replaced, since the checkpoint holds those weights."""
        super()._parse_ckpt_path()
        sub = self.config.get("subcommand")
        cfg = self.config.get(sub) if sub else None
        ckpt = cfg.get("ckpt_path") if cfg is not None else None
        model = cfg.get("model") if cfg is not None else None
        if not ckpt or not Path(str(ckpt)).is_file() or model is None:
            return
        for args_key in ("init_args", "dict_kwargs"):
            args = model.get(args_key) if hasattr(model, "get") else None
            if args is None or not hasattr(args, "get"):
                continue
            for key, replacement in (("encoder_ckpt", str(ckpt)), ("bank_ckpt", str(ckpt)), ("detector_ckpt", None),
                                     ("init_bank_ckpt", None)):
                value = args.get(key)
                if isinstance(value, str) and value and not Path(value).is_file():
                    args[key] = replacement

    def before_instantiate_classes(self) -> None:
        """Hold the run's ``trainer.default_root_dir`` (:func:`~threedq.locks.hold_folder`), and make a bf16
        ``trainer.precision`` ``32-true`` on a CPU without bf16 instructions, saying so in one line."""
        trainer = self._get(self.config, "trainer", default=None)
        if trainer is not None:
            precision, note = cpu_precision(trainer.get("precision"), _runs_on_cpu(trainer))
            if note is not None:
                trainer["precision"] = precision
                print(f"[threedq] {note}", flush=True)
        if self.subcommand is not None:
            root = self._get(self.config, "trainer", default={}).get("default_root_dir") or DEFAULT_ROOT
            self._hold.enter_context(hold_folder(root))

    def instantiate_classes(self) -> None:
        try:
            super().instantiate_classes()
        except Exception as e:
            inner = user_error_in_chain(e)
            if inner is not None:
                raise inner from None
            raise
        if self._model_setup is not None:
            self._model_setup(self.model)

    def instantiate_trainer(self, **kwargs: Any) -> L.Trainer:
        """Give every run a self-contained folder ``trainer.default_root_dir``: unless the config names its own, the
        loggers (TensorBoard + CSV) write into it and ``checkpoints/last.ckpt`` is kept there every 100 steps."""
        cfg = self._get(self.config_init, "trainer", default={})
        if cfg.get("sync_batchnorm") and _runs_on_cpu(cfg):
            raise ConfigError("--trainer.sync_batchnorm: SyncBatchNorm runs on GPUs only; on CPU use --config "
                              "trainer/ddp_cpu.yaml (or --trainer.sync_batchnorm false)")
        if cfg.get("strategy") == "ddp":
            kwargs["strategy"] = DDPStrategy()
        root = Path(cfg.get("default_root_dir") or DEFAULT_ROOT)
        if cfg.get("logger") in (None, True) and not cfg.get("fast_dev_run"):
            kwargs["logger"] = [TensorBoardLogger(save_dir=str(root), name="", version=""),
                                CSVLogger(save_dir=str(root), name="", version="")]
        callbacks = list(cfg.get("callbacks") or [])
        if cfg.get("enable_checkpointing") is not False and not any(isinstance(c, ModelCheckpoint) for c in callbacks):
            ckpt = LastStepCheckpoint(dirpath=root / "checkpoints", save_last=True, every_n_train_steps=100)
            kwargs["callbacks"] = [*callbacks, ckpt]
        if not cfg.get("plugins"):
            kwargs["plugins"] = [AtomicCheckpointIO()]
        return super().instantiate_trainer(**kwargs)


def test_checkpoint(
    configs: Sequence[str | Path], ckpt: str | Path, out_dir: str | Path, overrides: Sequence[str] = (),
    model_setup: Callable[[L.LightningModule], None] | None = None) -> tuple[ThreeDQCLI, dict[str, float]]:
    """Score a stage checkpoint through the stage's own ``test_step`` (built from ``configs`` with ``encoder_ckpt`` =
    ``ckpt``), without a logger, in ``out_dir``.

    Returns:
        The CLI (its ``model`` and ``datamodule`` are set up and loaded, for further evaluation) and the test
        metrics the stage logged, ``{"test/<name>": value}``.
    """
    args = [a for c in configs for a in ("--config", str(c))]
    args += [*overrides, f"--model.init_args.encoder_ckpt={ckpt}", "--trainer.logger=false",
             "--trainer.enable_checkpointing=false", f"--trainer.default_root_dir={out_dir}"]
    cli = ThreeDQCLI(args=args, run=False, model_setup=model_setup)
    results = cli.trainer.test(cli.model, datamodule=cli.datamodule, ckpt_path=str(ckpt), verbose=False,
                               weights_only=True)
    return cli, {k: float(v) for k, v in (results[0] if results else {}).items()}
