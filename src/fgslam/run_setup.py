"""One run as ``fgslam run`` makes it, for the API and every benchmark that runs passes.

From a traverse's inputs and a :class:`fgslam.compare.CompareConfig`: the ground truth, the span
that decides whether it is a long traverse, the runner's config (checked against the stream,
:func:`fgslam.inputs.check_stream`, and :func:`fgslam.long_traverse.runner_config_for`), the
back-ends' overrides (the config's, :func:`fgslam.long_traverse.backend_overrides_for`) and the
relocalizers (:func:`fgslam.compare.relocalizer_set`: rocks with ``relocalizer``, every other
kind with ``kind_relocalizers``, heights from a terrain model). A benchmark that changes one of
these for a pass (a kind left out, a setting varied) says so through :meth:`RunSetup.backend`'s
``extra`` and :meth:`RunSetup.relocalizers`' ``kinds``; everything else is what ``fgslam run``
would do with the same directory and ``--config``.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any


def first_seconds(measurements: Iterable, duration_s: float | None) -> Iterator:
    """The measurements of the first ``duration_s`` seconds (all of them for None), lazily."""
    if duration_s is None:
        yield from measurements
        return
    t_end = None
    for m in measurements:
        if t_end is None:
            t_end = m.t + duration_s
        if m.t > t_end:
            return
        yield m


@dataclass
class RunSetup:
    """What a run over ``inputs`` (:class:`fgslam.inputs.RunInputs`) with ``cfg`` gets (module
    doc); ``duration_s`` cuts the stream to its first seconds (None: all of it), and the
    long-traverse decision follows the cut."""

    inputs: Any
    cfg: Any
    gt: Any
    span_s: float
    runner: Any
    duration_s: float | None = None

    @classmethod
    def of(cls, inputs, cfg, duration_s: float | None = None) -> RunSetup:
        from fgslam.inputs import check_stream, truth_of
        from fgslam.long_traverse import run_span_s, runner_config_for

        gt = truth_of(inputs)
        span = run_span_s(gt, inputs.measurements, duration_s)
        runner = runner_config_for(check_stream(inputs, cfg.runner), span, cfg.long_traverse)
        return cls(inputs, cfg, gt, span, runner, duration_s)

    @classmethod
    def of_directory(cls, directory: Path, config: Path | None = None, duration_s: float | None = None) -> RunSetup:
        """An ``fgslam sim`` directory with ``config`` (None: the directory's ``backend.yaml`` when it
        has one, as ``fgslam run DIR`` takes it)."""
        from fgslam.cli.cmd_run import sim_dir_config
        from fgslam.config_file import load_compare_config
        from fgslam.inputs import bag_topics, load_sim_dir

        cfg = load_compare_config(sim_dir_config(Path(directory), config))
        return cls.of(load_sim_dir(Path(directory), topics=bag_topics(cfg.topics), images=cfg.images), cfg, duration_s)

    def overrides(self, name: str, extra: dict | None = None) -> dict:
        """Back-end ``name``'s overrides: the config's, ``extra`` merged over them, then what a long
        traverse adds."""
        from fgslam.long_traverse import backend_overrides_for
        from reloc.config import merged_overrides

        over = merged_overrides(dict(self.cfg.backend_overrides.get(name) or {}), dict(extra or {}))
        return backend_overrides_for(name, over, self.span_s, self.cfg.long_traverse)

    def backend(self, name: str, extra: dict | None = None):
        """A new back-end ``name`` at the inputs' start, with :meth:`overrides`."""
        from fgslam.backends.registry import make_backend

        return make_backend(name, self.inputs.initial, self.overrides(name, extra))

    def relocalizers(self, kinds: Iterable[str] | None = None) -> list:
        """The run's relocalizers (module doc), only those of ``kinds`` when given (the others are
        not built)."""
        from fgslam.compare import relocalizer_set

        if kinds is None:
            return relocalizer_set(self.inputs, self.cfg)
        wanted = set(kinds)
        inputs = replace(self.inputs, catalogs={k: c for k, c in self.inputs.catalogs.items() if k in wanted})
        cfg = replace(self.cfg, kind_relocalizers={k: v for k, v in self.cfg.kind_relocalizers.items()
                                                   if k in wanted})
        return relocalizer_set(inputs, cfg)

    def measurements(self) -> Iterator:
        """The stream, cut to ``duration_s`` (a new iterator at every call)."""
        return first_seconds(self.inputs.measurements, self.duration_s)

    def run(self, backend, fixes=None, **kwargs):
        """:func:`fgslam.runner.run_backend` of ``backend`` over :meth:`measurements` with ``fixes``
        (None: none) and the runner's config; ``kwargs`` go to it (``on_progress``, ``observer``)."""
        from fgslam.fix_sources import NoFixes
        from fgslam.runner import run_backend

        return run_backend(backend, self.measurements(), fixes if fixes is not None else NoFixes(),
                           config=self.runner, keep_truth=False, **kwargs)
