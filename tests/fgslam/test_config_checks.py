"""Configs are checked by type and range when they are loaded, naming the key, and a saved
config.yaml is accepted back by --config (issue 17, case 3)."""

from __future__ import annotations

import dataclasses

import pytest

from ekf.config import EkfConfig, FixGateConfig
from fgslam.backends.dead_reckoning import DeadReckoningConfig
from fgslam.compare import CompareConfig, CompareError
from fgslam.config_file import compare_overrides, load_compare_config, sim_overrides
from fgslam.relocalizer import RelocalizerConfig, RelocalizerError
from fgslam.runner import RunnerConfig, RunnerError
from fgslam.smoother.config import SmootherConfig
from reloc.config import config_from_dict, config_to_dict
from reloc.errors import ConfigError
from reloc.matcher import MatcherConfig
from sim.config import SimConfig

# (YAML text, what the error must say): every bad config of the issue, and a few more
BAD = [
    ('relocalizer: {track: "no"}', "relocalizer.track"),
    ("relocalizer: {period_s: .nan}", "relocalizer.period_s must be finite, got nan"),
    ("relocalizer: {max_radius_m: .nan}", "relocalizer.max_radius_m must be finite"),
    ("relocalizer: {period_s: fast}", "relocalizer.period_s must be a number, got 'fast'"),
    ('relocalizer: {period_s: "2.0"}', "relocalizer.period_s must be a number, got '2.0'"),
    ("relocalizer: {max_landmarks: 2.5}", "relocalizer.max_landmarks must be an integer, got 2.5"),
    ("relocalizer: 5", "relocalizer must be a mapping"),
    ("runner: .nan", "runner must be a mapping"),
    ("backend_overrides: {foo: {}}", "backend_overrides.foo: unknown back-end 'foo'"),
    ("relocalizer: {inflation: 0}", "relocalizer.inflation must be >= 1, got 0"),
    ("relocalizer: {sigma_floor_m: -0.01}", "relocalizer.sigma_floor_m must be >= 0"),
    ("relocalizer: {period_s: .inf}", "relocalizer.period_s must be finite, got inf"),
    ("relocalizer: {delay_s: .nan}", "relocalizer.delay_s must be finite, got nan"),
    ("relocalizer: {select: biggest}", "relocalizer.select must be one of ['largest', 'nearest']"),
    ("relocalizer: {matcher: {sigma_m: 0}}", "matcher.sigma_m must be > 0"),
    ("relocalizer: {matcher: {sigmam: 0.1}}", "unknown key 'matcher.sigmam'"),
    ("runner: {max_imu_gap_s: -1}", "runner.max_imu_gap_s must be > 0"),
    ("runner: {speed_source: wheels}", "runner.speed_source must be one of ['cmd', 'wheel']"),
    ("backend_overrides: {ekf: {max_landmarks: 0}}", "backend_overrides.ekf.max_landmarks must be >= 1"),
    ("backend_overrides: {ekf: {fix_gate: {chi2: -3}}}", "backend_overrides.ekf.fix_gate.chi2 must be > 0"),
    ("backend_overrides: {isam2: {factorization: lu}}", "backend_overrides.isam2.factorization"),
    ("backend_overrides: {isam2: {fixes: {gate_chi2: .nan}}}", "backend_overrides.isam2.fixes.gate_chi2 must be finite"),
    ("backend_overrides: {dr: 3}", "backend_overrides.dr must be a mapping"),
    ("backends: [ekf, kalman]", "unknown back-end(s) ['kalman']"),
    ("workers: 0", "workers must be >= 1"),
    ("rpe_delta_m: true", "rpe_delta_m must be a number, got True"),
    ("relocaliser: {}", "unknown key 'relocaliser'"),
]


@pytest.mark.parametrize(("text", "message"), BAD)
def test_a_bad_value_is_named_when_the_file_is_loaded(tmp_path, text, message):
    path = tmp_path / "cfg.yaml"
    path.write_text(text + "\n")
    with pytest.raises(ConfigError) as err:
        load_compare_config(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_every_error_of_a_file_is_listed_and_good_values_pass(tmp_path):
    path = tmp_path / "cfg.yaml"
    path.write_text("relocalizer: {period_s: fast, max_landmarks: 2.5, track: true}\nrunner: {max_imu_gap_s: 3}\n")
    with pytest.raises(ConfigError, match="period_s.*max_landmarks|max_landmarks.*period_s"):
        load_compare_config(path)
    path.write_text("relocalizer: {period_s: 3, track: true, fit_radius_m: null}\nbackend_overrides: {isam2: {factorization: qr}}\n")
    cfg = load_compare_config(path)
    assert cfg.relocalizer.period_s == 3.0 and isinstance(cfg.relocalizer.period_s, float)
    assert cfg.relocalizer.track is True and cfg.relocalizer.fit_radius_m is None


@pytest.mark.parametrize("cls", [CompareConfig, RunnerConfig, RelocalizerConfig, EkfConfig, SmootherConfig,
                                 DeadReckoningConfig, MatcherConfig, SimConfig])
def test_defaults_are_valid_and_round_trip(cls):
    cfg = cls()
    assert config_from_dict(cls, {}) == cfg
    assert config_from_dict(cls, config_to_dict(cfg)) == cfg


def test_a_partial_section_keeps_the_fields_own_defaults():
    # the smoother's budget default (25, 3) differs from ObservationBudget's own (0, 0)
    cfg = config_from_dict(SmootherConfig, {"landmarks": {"budget": {"max_new": 2}}})
    assert (cfg.landmarks.budget.max_observations, cfg.landmarks.budget.max_new) == (25, 2)


@pytest.mark.parametrize(("build", "error", "message"), [
    (lambda: RelocalizerConfig(period_s=float("nan")), RelocalizerError, "RelocalizerConfig.period_s must be finite"),
    (lambda: RelocalizerConfig(inflation=0.5), RelocalizerError, "inflation must be >= 1"),
    (lambda: RelocalizerConfig(matcher={"sigma_m": -1.0}), RelocalizerError, "matcher.sigma_m must be > 0"),
    (lambda: RunnerConfig(max_speed_age_s=0.0), RunnerError, "max_speed_age_s must be > 0"),
    (lambda: FixGateConfig(yaw_deg=float("inf")), ConfigError, "yaw_deg must be finite"),
    (lambda: dataclasses.replace(EkfConfig(), history_s=-1.0), ConfigError, "EkfConfig.history_s must be > 0"),
    (lambda: CompareConfig(backends=("ekf", "kalman")), CompareError, "kalman"),
    (lambda: CompareConfig(backend_overrides={"ekf": {"max_landmarks": "many"}}), ConfigError, "max_landmarks"),
])
def test_configs_built_in_code_are_checked_too(build, error, message):
    with pytest.raises(error, match=message.replace("(", r"\(").replace(")", r"\)")):
        build()


def test_saved_run_and_compare_configs_are_accepted_back(tmp_path):
    """The shapes `fgslam run` and `fgslam compare` write (the e2e test writes real ones)."""
    ekf = config_to_dict(EkfConfig(max_landmarks=80))
    run_saved = {"backend": "ekf", "relocalization": True, "inputs": {"kind": "bag", "bag": "x"},
                 "runner": config_to_dict(RunnerConfig(record_rate_hz=5.0)),
                 "relocalizer": config_to_dict(RelocalizerConfig(period_s=3.0)), "backend_config": ekf}
    cfg = config_from_dict(CompareConfig, compare_overrides(run_saved))
    assert cfg.runner.record_rate_hz == 5.0 and cfg.relocalizer.period_s == 3.0
    assert config_from_dict(EkfConfig, cfg.backend_overrides["ekf"]) == EkfConfig(max_landmarks=80)
    cmp_saved = {"config": config_to_dict(dataclasses.replace(CompareConfig(), workers=1)), "inputs": [{"dir": "d"}]}
    assert config_from_dict(CompareConfig, compare_overrides(cmp_saved)).workers == 1
    world_yaml = {"world": "cnes", "seed": 3, "extent": [0, 1, 0, 1], "stats": {},
                  "config": config_to_dict(dataclasses.replace(SimConfig(), world="cnes", seed=3))}
    assert config_from_dict(SimConfig, sim_overrides(world_yaml)).seed == 3
    with pytest.raises(ConfigError, match="unknown key 'stats'"):  # a world.yaml is not a compare config
        config_from_dict(CompareConfig, compare_overrides(world_yaml))
