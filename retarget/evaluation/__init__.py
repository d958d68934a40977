"""The evaluation protocol of the paper (Sec. IV-A), independent of the solver.

One concept per module: ``config`` (settings), ``alignment`` (time), ``scale`` (world scale),
``units`` (body units), ``channels`` (objects), ``proximity`` (exact distances), ``contact``
(H, R, P, R, J, dd, dw), ``orientation`` (rot), ``self_collision`` (self), ``feet`` (skate,
clear), ``sequence`` (one reference, dataset medians), ``report`` / ``plots`` / ``cli``.
``retarget.metrics`` is the public entry point.
"""
