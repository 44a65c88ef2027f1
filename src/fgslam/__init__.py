"""fgslam: iSAM2 smoother and the application (bags, runner, metrics, rerun, CLI).

The facade (:mod:`fgslam.api`), imported on first use so that ``import fgslam`` stays light:
``fgslam.simulate(world, out)``, ``fgslam.run(sim_dir)``, ``fgslam.compare([sim_dir])``.
``fgslam.compare`` is also the comparison module (``fgslam.compare.CompareConfig``); calling it
calls :func:`fgslam.api.compare`.
"""

from fgslam.errors import FgslamError

__version__ = "0.1.0"
__all__ = ["FgslamError", "__version__", "compare", "run", "simulate"]


def __getattr__(name: str):
    if name in ("simulate", "run"):
        from fgslam import api

        return getattr(api, name)
    if name == "compare":
        import importlib

        return importlib.import_module("fgslam.compare")
    raise AttributeError(f"module 'fgslam' has no attribute {name!r}")
