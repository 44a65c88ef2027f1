"""What a Monte Carlo campaign is: worlds x seeds x config variants, and the tasks it expands to.

Overrides are dotted keys on the simulator config (:class:`sim.config.SimConfig`, e.g.
``traverse.distance_m`` or ``sensors.stereo.sigma_pixel_px``) or on the comparison config
(:class:`fgslam.compare.CompareConfig`, e.g. ``relocalizer.period_s``); the two sets of top-level
names are disjoint, so a key finds its config by its first component (an explicit ``sim.`` or
``compare.`` prefix is accepted too). A task is a small JSON-ready dict: world, seed, variant and
the merged overrides, identified by ``(world, variant, seed)`` plus a hash of its overrides.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
import re
from dataclasses import dataclass, field

from fgslam.errors import FgslamError

BASE_VARIANT = "base"
# Campaign axes (world, seed) and the in-task parallelism are not overridable per task.
_FORBIDDEN = {"sim.world": "use --worlds", "sim.seed": "use --seeds",
              "compare.workers": "tasks run their passes in one process; scale with --workers"}


class CampaignError(FgslamError):
    """A campaign is malformed (seeds, overrides), its results file is unusable, or Dask is missing."""


@dataclass(frozen=True)
class CampaignSpec:
    """``worlds`` (preset names or Gazebo model directories) x ``seeds`` (simulator seeds) x
    ``variants`` (name -> dotted overrides); ``overrides`` (dotted key -> value) apply to every task."""

    worlds: tuple[str, ...]
    seeds: tuple[int, ...]
    overrides: dict = field(default_factory=dict)
    variants: dict = field(default_factory=lambda: {BASE_VARIANT: {}})

    def to_dict(self) -> dict:
        """JSON-ready view (written to OUT/campaign.json)."""
        return {"worlds": list(self.worlds), "seeds": list(self.seeds), "overrides": dict(self.overrides),
                "variants": {k: dict(v) for k, v in self.variants.items()}}


def parse_seeds(text: str) -> tuple[int, ...]:
    """"0-9", "0,3,7" or "0-3,10-12" -> sorted unique seeds (ranges inclusive)."""
    seeds: set[int] = set()
    for part in (p.strip() for p in str(text).split(",")):
        m = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not m:
            raise CampaignError(f"--seeds: {part!r} in {text!r} is not a seed or a range like 0-9")
        lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
        if hi < lo:
            raise CampaignError(f"--seeds: range {part!r} ends before it starts")
        seeds.update(range(lo, hi + 1))
    return tuple(sorted(seeds))


def parse_value(text: str):
    """A YAML scalar or flow collection ("3", "0.5", "true", "[1, 2]", "measured") -> Python value."""
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CampaignError(f"override value {text!r} is not valid YAML: {exc}") from exc
    if isinstance(value, str) and not value.strip().isalpha():  # YAML 1.1 reads 4e-9 (no dot) as a string
        try:
            return float(value)
        except ValueError:
            pass
    return value


def split_assignment(text: str) -> tuple[str, str]:
    """"key=value" -> (key, value text), the key stripped; raises naming the input when malformed."""
    key, sep, value = str(text).partition("=")
    if not sep or not key.strip():
        raise CampaignError(f"override {text!r} must look like key=value (e.g. relocalizer.period_s=5)")
    return key.strip(), value.strip()


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict:
    """["relocalizer.period_s=5", ...] -> {"compare.relocalizer.period_s": 5, ...} (canonical keys)."""
    out: dict = {}
    for item in items:
        key, value = split_assignment(item)
        out[canonical_key(key)] = parse_value(value)
    return out


def split_list(text: str) -> list[str]:
    """Split "2,3,[1, 2]" at the commas outside brackets -> ["2", "3", "[1, 2]"]."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        depth += ch in "[{"
        depth -= ch in "]}"
        if ch == "," and depth == 0:
            parts.append(cur.strip())
            cur = ""
        else:
            cur += ch
    parts.append(cur.strip())
    return [p for p in parts if p]


def variants_from_sweeps(items: list[str] | tuple[str, ...]) -> dict:
    """["relocalizer.period_s=2,5", ...] -> one variant per combination of the swept values
    (cartesian product), named "relocalizer.period_s=2" (joined by spaces); {"base": {}} when empty."""
    if not items:
        return {BASE_VARIANT: {}}
    axes = []
    for item in items:
        key, values = split_assignment(item)
        texts = split_list(values)
        if not texts:
            raise CampaignError(f"--vary {item!r}: no values to sweep")
        axes.append([(key, canonical_key(key), t, parse_value(t)) for t in texts])
    variants = {}
    for combo in itertools.product(*axes):
        name = " ".join(f"{key}={text}" for key, _, text, _ in combo)
        variants[name] = {canon: value for _, canon, _, value in combo}
    return variants


def _roots() -> dict[str, str]:
    from fgslam.compare import CompareConfig
    from sim.config import SimConfig

    roots = {f.name: "sim" for f in dataclasses.fields(SimConfig)}
    roots.update({f.name: "compare" for f in dataclasses.fields(CompareConfig)})
    return roots


def canonical_key(key: str) -> str:
    """"relocalizer.period_s" -> "compare.relocalizer.period_s"; "traverse.distance_m" -> "sim.traverse.distance_m"."""
    parts = key.split(".")
    if parts[0] not in ("sim", "compare"):
        root = _roots().get(parts[0])
        if root is None:
            known = ", ".join(sorted(_roots()))
            raise CampaignError(f"override key {key!r}: {parts[0]!r} is neither a simulator nor a comparison "
                                f"setting (top-level names: {known})")
        parts = [root, *parts]
    if len(parts) < 2 or not all(parts):
        raise CampaignError(f"override key {key!r} is malformed")
    canon = ".".join(parts)
    if ".".join(parts[:2]) in _FORBIDDEN:
        raise CampaignError(f"override key {key!r} cannot be set: {_FORBIDDEN['.'.join(parts[:2])]}")
    return canon


def nest(overrides: dict) -> dict:
    """{"compare.relocalizer.period_s": 5} -> {"compare": {"relocalizer": {"period_s": 5}}}; a key
    without its prefix finds it (:func:`canonical_key`), an unknown one is an error (a spec built in
    code with ``"traverse.distance_m"`` must not run the default traverse without a word)."""
    out: dict = {}
    for key, value in overrides.items():
        key = canonical_key(key)
        node = out
        *parents, leaf = key.split(".")
        for p in parents:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise CampaignError(f"override {key!r} conflicts with a value set on {p!r}")
            node = nxt
        if isinstance(node.get(leaf), dict):
            raise CampaignError(f"override {key!r} replaces a whole section set by other overrides")
        node[leaf] = copy.deepcopy(value)  # later keys may add to it; the spec stays untouched
    return out


def build_configs(overrides: dict, world: str | None = None, seed: int = 0, compare_base: dict | None = None):
    """(SimConfig, CompareConfig) from canonical dotted overrides. On a kilometre preset ``world``
    the simulator overrides apply to that preset's config for ``seed`` (as ``fgslam sim`` does);
    ``compare_base`` (the mapping of a run's ``backend.yaml``: the back-ends' calibration for its
    sensors) lies under the comparison overrides. World and seed are otherwise left at their
    defaults (the task sets them)."""
    from fgslam.compare import CompareConfig
    from reloc.config import config_from_dict, merged_overrides
    from sim.config import SimConfig
    from sim.tiled.presets import is_tiled, preset_config

    tree = nest(overrides)
    base = preset_config(world, seed) if world is not None and is_tiled(world) else None
    sim_cfg = config_from_dict(SimConfig, tree.get("sim"), base=base, where="sim.")
    # a task's backend_overrides.isam2.fixed_lag_s adds to a kilometre run's backend.yaml instead of
    # replacing its calibration
    cmp_tree = merged_overrides(compare_base or {}, tree.get("compare") or {})
    cmp_cfg = config_from_dict(CompareConfig, cmp_tree, where="compare.")
    return sim_cfg, dataclasses.replace(cmp_cfg, workers=1)


def config_hash(overrides: dict) -> str:
    """Short stable hash of a task's merged overrides (its identity across runs together with the key)."""
    text = json.dumps(overrides, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def task_key(world: str, variant: str, seed: int) -> str:
    """Readable identity of a task: "cnes/base/seed3"."""
    return f"{world}/{variant}/seed{int(seed)}"


def expand(spec: CampaignSpec) -> list[dict]:
    """Every task of ``spec`` (world-major, then variant, then seed), each checked to build its configs."""
    if not spec.worlds:
        raise CampaignError("a campaign needs at least one world")
    if not spec.seeds:
        raise CampaignError("a campaign needs at least one seed")
    if not spec.variants:
        raise CampaignError("a campaign needs at least one variant")
    from reloc.errors import RelocError
    from sim.config import validate
    from sim.errors import SimError
    from sim.tiled.presets import is_tiled

    # a yard's or Gazebo world's config does not depend on the world; a kilometre preset's does
    worlds = list(dict.fromkeys(spec.worlds))
    checked = ([None] if any(not is_tiled(w) for w in worlds) else []) + [w for w in worlds if is_tiled(w)]
    for name, var in spec.variants.items():
        for world in checked:
            try:
                sim_cfg, _ = build_configs({**spec.overrides, **var}, world, spec.seeds[0])
                validate(sim_cfg)
            except (RelocError, FgslamError, SimError, TypeError, ValueError) as exc:  # unknown keys, bad values
                on = "" if world is None else f" on {world}"
                raise CampaignError(f"variant {name!r}{on}: {exc}") from exc
    tasks = []
    for world in spec.worlds:
        for name, var in spec.variants.items():
            over = {**spec.overrides, **var}
            h = config_hash(over)
            for seed in spec.seeds:
                tasks.append({"key": task_key(world, name, seed), "world": world, "variant": name,
                              "seed": int(seed), "overrides": over, "config_hash": h})
    return tasks
