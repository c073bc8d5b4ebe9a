"""``threedq data generate|degrade|show|check|import|index``: the embedded dataset generator, sensor-like copies, a
contact sheet, a validator, the importer of on-disk capture formats and the index writer of a folder of scenes.

A bad option is refused with one line naming it (:class:`~threedq.errors.InputError`).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Literal

from jsonargparse import ArgumentParser

from threedq.data.contact_sheet import contact_sheet
from threedq.data.folder_index import index_folder
from threedq.data.formats.importer import import_captures
from threedq.data.formats.registry import FORMATS
from threedq.data.generate import generate_dataset
from threedq.data.generator_config import GeneratorConfig
from threedq.data.sensor import EFFECTS, degrade_dataset
from threedq.errors import InputError
from threedq.scene import SceneValidationError, load_index, load_scene

__all__ = ["check_dataset", "data_parsers", "output_folder", "run_data"]

#: ``generate``: the name an argument of GeneratorConfig / generate_dataset has as a command-line option.
_GENERATE_OPTIONS = {"num_scenes": "scenes", "num_views": "views", "splits": "split"}


def output_folder(option: str, path: str | Path) -> Path:
    """``path`` as an output folder: refused (one line naming ``option``) if it exists and is not a folder, or if
    it, or a folder above it, cannot be made."""
    p = Path(path)
    for q in (p, *p.parents):
        if q.exists():
            if not q.is_dir():
                what = "exists and is not a folder" if q == p else f"cannot be made: {q} is a file, not a folder"
                raise InputError(f"{option} {p}: {what}")
            break
    return p


def _option_error(e: ValueError, names: dict[str, str]) -> InputError:
    """A ValueError of a library function (``name: reason``) as an InputError naming the command-line option."""
    text = str(e).splitlines()[0] if str(e) else type(e).__name__
    m = re.match(r"([A-Za-z_][\w, ]*?): (.*)$", text)
    if not m:
        return InputError(text)
    opts = ", ".join(f"--{names.get(n.strip(), n.strip())}" for n in m.group(1).split(","))
    return InputError(f"{opts}: {m.group(2)}")


FormatName = Literal[tuple(FORMATS)]  # type: ignore[valid-type]


def data_parsers() -> list[tuple[str, ArgumentParser, str]]:
    gen = ArgumentParser(description="Generate the embedded CLEVR-veggie-like dataset (offline, deterministic, "
                         "resumable).")
    gen.add_argument("--out", required=True, help="output dataset folder")
    gen.add_argument("--scenes", type=int, default=300, help="number of scenes over all generated splits")
    gen.add_argument("--seed", type=int, default=0, help="seed of the train/val scenes")
    gen.add_argument("--test_seed", type=int | None, default=None,
                     help="seed of the test scenes (default: derived from --seed)")
    gen.add_argument("--split", type=list[str], default=["train", "val", "test"], help="splits to generate")
    gen.add_argument("--split_fractions", type=tuple[float, float, float], default=(0.8, 0.1, 0.1))
    gen.add_argument("--image_size", type=tuple[int, int], default=(128, 128), help="[H, W] in pixels")
    gen.add_argument("--views", type=int, default=28, help="cameras per scene")
    gen.add_argument("--min_objects", type=int, default=1)
    gen.add_argument("--max_objects", type=int, default=3)
    gen.add_argument("--categories", type=list[str] | None, default=None, help="category names to use (default all 41)")
    d = GeneratorConfig()
    gen.add_argument("--color_mode", type=Literal["category", "random"], default="category",
                     help="'category': catalogue colours; 'random': a random palette colour per instance (shape-only)")
    gen.add_argument("--object_size", type=float, default=d.object_size,
                     help="largest extent of an object before its random scale, metres")
    gen.add_argument("--scale_range", type=tuple[float, float], default=d.scale_range,
                     help="random object scale (low, high)")
    gen.add_argument("--placement_radius", type=float, default=d.placement_radius,
                     help="object centres lie within this distance of the origin, metres")
    gen.add_argument("--distance_range", type=tuple[float, float], default=d.distance_range,
                     help="camera distance to the look-at point (low, high), metres")
    gen.add_argument("--fov_deg", type=float, default=d.fov_deg, help="horizontal field of view, degrees")
    gen.add_argument("--elevation_range_deg", type=tuple[float, float], default=d.elevation_range_deg,
                     help="camera elevation above the ground (low, high), degrees")
    gen.add_argument("--capture_level", type=float, default=0.0,
                     help="sensor-like capture conditions (depth noise, quantisation, dropout, exposure, pose drift, "
                     "gravity tilt; threedq.data.sensor): 0 = clean renders, 1 = a typical RGB-D camera, 2 = twice "
                     "that; the layouts are those of the clean set of the same seed")
    gen.add_argument("--capture_effects", type=list[str] | None, default=None,
                     help="which capture conditions to apply (default all: " + ", ".join(EFFECTS) + ")")
    gen.add_argument("--workers", type=int, default=2, help="rendering processes")
    gen.add_argument("--progress", type=bool, default=True)

    deg = ArgumentParser(description="Write a copy of a dataset folder with sensor-like capture conditions "
                         "(threedq.data.sensor): what a sensor and its tracker would make of the same scenes.")
    deg.add_argument("dir", help="dataset folder")
    deg.add_argument("--out", required=True, help="the copy's folder (a killed run resumes)")
    deg.add_argument("--capture_level", type=float, default=1.0,
                     help="1 = a typical RGB-D camera and tracker, 2 = twice that")
    deg.add_argument("--capture_effects", type=list[str] | None, default=None,
                     help="which capture conditions to apply (default all: " + ", ".join(EFFECTS) + ")")
    deg.add_argument("--seed", type=int, default=0, help="seed of the copy's draws (with each scene's path)")
    deg.add_argument("--splits", type=list[str] | None, default=None,
                     help="degrade only these splits (e.g. [test]: a trained model meets a noisy test set); the "
                     "others are copied unchanged (default: all)")
    deg.add_argument("--progress", type=bool, default=True)

    show = ArgumentParser(description="Draw a contact sheet (rgb, depth, instances, GT boxes) of a dataset.")
    show.add_argument("dir", help="dataset folder")
    show.add_argument("--out", required=True, help="PNG to write")
    show.add_argument("--scenes", type=int, default=4)
    show.add_argument("--split", type=str | None, default=None)
    show.add_argument("--views", type=list[int] | None, default=None, help="view indices per scene (default: a few)")
    show.add_argument("--upscale", type=int, default=3, help="pixel upscaling of each view")

    check = ArgumentParser(description="Validate every scene of a dataset folder; one line per bad file.")
    check.add_argument("dir", help="dataset folder")

    imp = ArgumentParser(description="Import RGB-D captures of an on-disk format (README 'Real captures') as canonical "
                         "scenes: z up, centred, subsampled views; writes <out>/<split>/*.npz and index.json.")
    imp.add_argument("src", help="one capture folder, or a folder of them")
    imp.add_argument("--format", type=FormatName, required=True, help="capture format")
    imp.add_argument("--out", required=True, help="output dataset folder (an existing index is extended)")
    imp.add_argument("--split", type=Literal["train", "val", "test"], default="train")
    imp.add_argument("--max_views", type=int, default=28, help="views kept per scene (farthest camera positions)")
    imp.add_argument("--max_depth", type=float, default=10.0, help="depth beyond this many metres becomes 0")
    imp.add_argument("--intrinsics", type=tuple[float, float, float, float] | None, default=None,
                     help="fx fy cx cy (tum: overrides the sensor's constants)")
    imp.add_argument("--depth_units_per_metre", type=float | None, default=None,
                     help="overrides the format's depth scale")
    imp.add_argument("--max_dt", type=float | None, default=None, help="tum: timestamp association tolerance, seconds")
    imp.add_argument("--progress", type=bool, default=True)

    idx = ArgumentParser(description="Write index.json for a folder of canonical scene .npz files.")
    idx.add_argument("dir", help="dataset folder (split = first sub-folder: train/, val/, test/)")
    idx.add_argument("--categories", type=list[str] | None, default=None, help="names by id (default category_<id>)")
    idx.add_argument("--symmetry_order", type=list[int] | None, default=None, help="per category (default 1: none)")
    idx.add_argument("--default_split", type=Literal["train", "val", "test"], default="train")
    idx.add_argument("--margin", type=float, default=0.05, help="metres around the bounds taken from the data")

    return [("generate", gen, "generate the embedded dataset"),
            ("degrade", deg, "write a copy of a dataset with sensor-like capture conditions"),
            ("show", show, "draw a contact sheet PNG"), ("check", check, "validate a dataset folder"),
            ("import", imp, "import captures of an on-disk RGB-D format"),
            ("index", idx, "write index.json for a folder of canonical scenes")]


def run_data(cfg) -> int:  # noqa: ANN001 - jsonargparse Namespace
    action = cfg.action
    args = cfg[action]
    if action == "generate":
        out = output_folder("--out", args.out)
        try:
            config = GeneratorConfig(
                image_size=tuple(args.image_size), num_views=args.views, min_objects=args.min_objects,
                max_objects=args.max_objects, categories=tuple(args.categories) if args.categories else None,
                object_size=args.object_size, color_mode=args.color_mode, scale_range=tuple(args.scale_range),
                placement_radius=args.placement_radius, distance_range=tuple(args.distance_range),
                fov_deg=args.fov_deg, elevation_range_deg=tuple(args.elevation_range_deg),
                capture_level=args.capture_level,
                capture_effects=tuple(args.capture_effects) if args.capture_effects is not None else None)
            index = generate_dataset(out, num_scenes=args.scenes, seed=args.seed, config=config,
                                     split_fractions=tuple(args.split_fractions), test_seed=args.test_seed,
                                     splits=tuple(args.split), workers=args.workers, progress=args.progress)
        except InputError:
            raise
        except ValueError as e:
            raise _option_error(e, _GENERATE_OPTIONS) from e
        counts = {s: len(index.files(s)) for s in ("train", "val", "test")}
        print(f"wrote {sum(counts.values())} scenes to {args.out} "
              f"({', '.join(f'{k} {v}' for k, v in counts.items())})")
        return 0
    if action == "degrade":
        out = output_folder("--out", args.out)
        try:
            n = degrade_dataset(args.dir, out, args.capture_level, args.capture_effects, seed=args.seed,
                                progress=args.progress, splits=args.splits)
        except ValueError as e:
            raise _option_error(e, {"level": "capture_level", "effects": "capture_effects", "out": "out",
                                    "splits": "splits"}) from e
        print(f"wrote {n} scenes to {out} (capture level {args.capture_level:g}); read it as sensor captures: a data "
              f"config with SceneFolderDataModule (data_dir: {out}), or sensor_captures: true for another DataModule")
        return 0
    if action == "show":
        if Path(args.out).is_dir():
            raise InputError(f"--out {args.out}: is a folder; give the PNG file to write")
        output_folder("--out", Path(args.out).parent)
        out = contact_sheet(args.dir, args.out, num_scenes=args.scenes, views=args.views, split=args.split,
                            upscale=args.upscale)
        print(f"wrote {out}")
        return 0
    if action == "check":
        return check_dataset(args.dir)
    if action == "import":
        output_folder("--out", args.out)
        options = {"intrinsics": args.intrinsics, "depth_units_per_metre": args.depth_units_per_metre,
                   "max_dt": args.max_dt}
        try:
            summary = import_captures(args.format, args.src, args.out, split=args.split, max_views=args.max_views,
                                      max_depth=args.max_depth, reader_options=options, progress=args.progress)
        except InputError:
            raise
        except ValueError as e:
            print(f"threedq: error: {e}", file=sys.stderr)
            return 2
        for line in summary.lines():
            print(line)
        return 0 if summary.scenes else 1
    if action == "index":
        index, problems = index_folder(args.dir, categories=args.categories, symmetry_order=args.symmetry_order,
                                       default_split=args.default_split, margin=args.margin)
        for line in problems:
            print(line)
        counts = {s: len(index.files(s)) for s in ("train", "val", "test")}
        print(f"wrote {Path(args.dir) / 'index.json'}: {len(index.scenes)} scenes "
              f"({', '.join(f'{k} {v}' for k, v in counts.items())}), {len(index.categories)} categories, "
              f"bounds {list(index.scene_bounds[0])} .. {list(index.scene_bounds[1])}")
        return 0
    raise AssertionError(action)


def check_dataset(folder: str | Path) -> int:
    """Validate ``folder/index.json`` and every scene it lists; print one line per bad file. Returns 0 if all good."""
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
