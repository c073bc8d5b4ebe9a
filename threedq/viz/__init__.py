"""Every picture threedq draws, in one package (core layer: stages and the pipeline draw through it).

- :mod:`threedq.viz.png` — PNG bytes and atomic PNG files of RGB images and matplotlib figures (matplotlib's
  object API on an Agg canvas: no pyplot, the global backend is never set);
- :mod:`threedq.viz.detection` — detections against the GT, self-labels, objects found per size band;
- :mod:`threedq.viz.features` — view prediction, mined pairs, retrieval, rotational alignment, per-category
  retrieval;
- :mod:`threedq.viz.curves` — Table 3 against the round, accuracy against K;
- :mod:`threedq.viz.overview` — the README's picture: a scene's boxes and the prototypes they fall into.

Drawing primitives (projected boxes, depth and instance colouring, bird's-eye views of crops) are in
:mod:`threedq.data.draw`; the dataset contact sheet (``threedq data show``) in :mod:`threedq.data.contact_sheet`;
pictures rendered by the view decoder (``threedq parse``) in :mod:`threedq.pipeline.renders`.
"""

from threedq.viz.png import figure_png, new_figure, rgb_png, write_png

__all__ = ["figure_png", "new_figure", "rgb_png", "write_png"]
