"""warptan.kernels: the ``@wp.func`` and ``@wp.kernel`` layer of warptan (no allocation, no host logic).

Installed as ``warptan.kernels`` (the top-level name ``kernels`` belongs to another PyPI package and is
never imported). One topic per module; the conventions are those of :mod:`warptan` (design notes §1).
"""
