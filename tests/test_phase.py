"""Pixel-phase (S-curve) calibration from a log's own stars: estimator, simulated PSFs, the centroid stage."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from starlog.centroiding import extract_stars
# private _applied: the three-standard-error edge of an amplitude, which estimated amplitudes cannot reach exactly
from starlog.centroiding.phase import (
    PhaseCalibration,
    _applied,
    distinct_samples,
    estimate_phase_calibration,
    load_phase_calibrations,
    phase_samples,
)
from starlog.cli import cli
from starlog.errors import InvalidInputError
from starlog import topics
from starlog.facts import log_facts
from starlog.cli.describe import info_text
from starlog.io.reader import LogReader
from starlog.sim import CameraModel, SimulationConfig, Simulator
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log


def _s_curved(rng: np.random.Generator, n: int, amplitude: float, noise: float = 0.01):
    """True positions uniform in phase, and measured ones pulled by ``amplitude sin(2 pi p)`` plus noise."""
    true = rng.uniform(0.0, 500.0, (2, n))
    measured = true + amplitude * np.sin(2 * np.pi * true) + rng.normal(0.0, noise, true.shape)
    return true, measured


def test_estimate_recovers_an_s_curve_and_removes_it() -> None:
    rng = np.random.default_rng(5)
    true, measured = _s_curved(rng, 3000, -0.04)
    cal = estimate_phase_calibration(measured[0], measured[1], np.full(3000, 0.01), method="X")
    assert cal.n_stars > 2950 and cal.active  # a few share a 0.5 px cell
    assert cal.estimate_x[0] == pytest.approx(-0.04, abs=3 * cal.error_x[0])
    assert cal.amplitude_x == cal.amplitude_y  # the axes agree: one amplitude from both
    x, y = cal.apply(measured[0], measured[1])
    before = np.sqrt(np.mean((measured - true) ** 2))
    after = np.sqrt(np.mean((np.stack([x, y]) - true) ** 2))
    assert after < 0.6 * before


def test_no_s_curve_leaves_positions_unchanged() -> None:
    rng = np.random.default_rng(6)
    _, measured = _s_curved(rng, 3000, 0.0)
    cal = estimate_phase_calibration(measured[0], measured[1], np.full(3000, 0.01))
    assert abs(cal.estimate_x[0]) < 3 * cal.error_x[0] and not cal.active
    x, y = cal.apply(measured[0], measured[1])
    assert np.array_equal(x, measured[0]) and np.array_equal(y, measured[1])


# private _applied: its edge (2.9 standard errors, 0 +- 0) cannot be reached exactly through estimated amplitudes
def test_an_amplitude_is_applied_only_above_three_standard_errors_and_shrunk() -> None:
    assert _applied(0.029, 0.01) == 0.0 and _applied(0.0, 0.0) == 0.0
    assert _applied(-0.04, 0.01) == pytest.approx(-0.04 * (1 - 1 / 16))


def test_a_second_harmonic_s_curve_is_estimated_and_removed() -> None:
    rng = np.random.default_rng(3)
    true = rng.uniform(0.0, 500.0, (2, 4000))
    measured = true + 0.03 * np.sin(4 * np.pi * true)
    cal = estimate_phase_calibration(measured[0], measured[1], harmonics=2)
    assert cal.amplitude_x[0] == 0.0 and cal.amplitude_x[1] == pytest.approx(0.03, abs=3 * cal.error_x[1])
    corrected = np.stack(cal.apply(measured[0], measured[1]))
    assert np.sqrt(np.mean((corrected - true) ** 2)) < 0.3 * np.sqrt(np.mean((measured - true) ** 2))
    with pytest.raises(InvalidInputError, match="harmonics must be >= 1"):
        estimate_phase_calibration(measured[0], measured[1], harmonics=0)


def test_axes_get_their_own_amplitude_only_when_they_differ() -> None:
    rng = np.random.default_rng(7)
    true = rng.uniform(0.0, 500.0, (2, 4000))
    measured = true + np.array([[-0.06], [0.0]]) * np.sin(2 * np.pi * true)
    cal = estimate_phase_calibration(measured[0], measured[1])
    assert cal.separate_axes == (True,)
    assert cal.amplitude_x[0] == pytest.approx(-0.06, abs=0.02) and cal.amplitude_y == (0.0,)


def test_each_distinct_star_counts_once_and_too_few_decline() -> None:
    rng = np.random.default_rng(8)
    x, y = rng.uniform(10, 500, 15), rng.uniform(10, 500, 15)
    frames = 40  # a static field: the same 15 phases in every frame
    xs = np.tile(x, frames) + rng.normal(0, 0.01, 15 * frames)
    ys = np.tile(y, frames) + rng.normal(0, 0.01, 15 * frames)
    dx, _, _ = distinct_samples(xs, ys, np.full(xs.size, 0.01))
    assert dx.size == 15  # one per star, a star on a cell edge too
    with pytest.raises(InvalidInputError, match="too few distinct star positions"):
        estimate_phase_calibration(xs, ys, np.full(xs.size, 0.01))


def test_a_static_field_with_noise_counts_each_star_once_and_estimates_without_bias() -> None:
    """Noise scatters a static star over the edges of a 0.5 px square: were each square a star, the stars at
    phases 0 and 1/2 (on the edges) would count twice or more, inflating the amplitude and shrinking its error."""
    rng = np.random.default_rng(9)
    stars, frames, noise = 400, 30, 0.03
    true = rng.uniform(10.0, 500.0, (2, stars))
    measured = true - 0.03 * np.sin(2 * np.pi * true)
    xs = np.tile(measured[0], frames) + rng.normal(0.0, noise, stars * frames)
    ys = np.tile(measured[1], frames) + rng.normal(0.0, noise, stars * frames)
    cal = estimate_phase_calibration(xs, ys, np.full(xs.size, noise))
    assert cal.n_stars == stars
    assert cal.error_x[0] == pytest.approx(1 / (np.pi * np.sqrt(2 * stars)), rel=0.1)
    assert cal.estimate_x[0] == pytest.approx(-0.03, abs=3 * cal.error_x[0])
    assert cal.estimate_y[0] == pytest.approx(-0.03, abs=3 * cal.error_y[0])


def test_calibration_round_trips_through_dict_and_file(tmp_path: Path) -> None:
    cal = PhaseCalibration("MOMENT", (-0.05,), (-0.04,), (-0.05,), (-0.04,), (0.01,), (0.01,), 300, (True,))
    assert PhaseCalibration.from_dict(json.loads(json.dumps(cal.to_dict()))) == cal
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({"phase_correction": {"calibrations": [cal.to_dict()]}}))
    assert load_phase_calibrations(path) == {"MOMENT": cal}
    path.write_text("[]")
    with pytest.raises(InvalidInputError, match="no phase calibration"):
        load_phase_calibrations(path)


@pytest.mark.parametrize("text, message", [
    ("{not json", "cannot read the phase calibration file"),
    ("[1, 2]", "not a phase calibration record"),
    ('["MOMENT"]', "not a phase calibration record"),
    ('[{"method": "MOMENT"}]', "not a phase calibration record"),
    ('{"method": "MOMENT", "amplitude_px": {"x": ["a"], "y": [0]}}', "not a phase calibration record"),
    ('{"method": "MOMENT", "amplitude_px": {"x": [], "y": []}}', "one finite number per harmonic"),
    ('{"method": "MOMENT", "amplitude_px": {"x": [0.01, 0.0], "y": [0.01]}}', "one finite number per harmonic"),
    ('{"method": "MOMENT", "amplitude_px": {"x": [NaN], "y": [0.0]}}', "one finite number per harmonic"),
    ('{"methods": ["MOMENT"]}', "holds no phase calibration"),
])
def test_a_bad_calibration_file_is_a_clear_error(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "cal.json"
    path.write_text(text)
    with pytest.raises(InvalidInputError, match=message):
        load_phase_calibrations(path)
    with pytest.raises(InvalidInputError, match="cannot read the phase calibration file"):
        load_phase_calibrations(tmp_path / "missing.json")


@dataclass(frozen=True)
class _Errors:
    """A calibration learnt from simulated frames, and the errors against the truth without and with it:
    RMS (px, each axis's mean offset removed) and the S-curve (regression on sin 2 pi of the true phase)."""

    calibration: PhaseCalibration
    rms: tuple[float, float]
    s_curve: tuple[float, float]


def _against_truth(measured: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    err = measured - truth
    err = err - err.mean(axis=1, keepdims=True)  # the simulator's truth is at the frame's start (drift)
    basis = np.sin(2 * np.pi * (truth - np.rint(truth))).ravel()
    return float(np.sqrt(np.mean(err**2))), float(basis @ err.ravel() / (basis @ basis))


def _simulated_errors(config: SimulationConfig, method: str, frames: int) -> _Errors:
    """Calibrate ``method`` on ``frames`` simulated frames and compare with the truth (stars within 0.5 px of
    a true position, unsaturated)."""
    sim = Simulator(config)
    measured, truth, samples = [], [], []
    for frame in sim.frames(0, frames):
        _, cen = extract_stars(frame.image, methods=[method], gain=config.camera.gain,
                               read_noise=config.camera.read_noise)
        table = cen[method]
        samples.append(phase_samples(table))
        d = np.hypot(table["x"][:, None] - frame.x[None], table["y"][:, None] - frame.y[None])
        k = np.argmin(d, axis=1)
        ok = (d[np.arange(k.size), k] < 0.5) & ((table["flags"] & 1) == 0)
        measured.append(np.stack([table["x"][ok], table["y"][ok]]))
        truth.append(np.stack([frame.x[k[ok]], frame.y[k[ok]]]))
    cal = estimate_phase_calibration(*(np.concatenate([s[i] for s in samples]) for i in range(3)), method=method)
    m, t = np.concatenate(measured, axis=1), np.concatenate(truth, axis=1)
    (rms0, s0), (rms1, s1) = _against_truth(m, t), _against_truth(np.stack(cal.apply(m[0], m[1])), t)
    return _Errors(cal, (rms0, rms1), (s0, s1))


def _drifting(**psf) -> SimulationConfig:
    """40 bright stars drifting 0.3 px per frame: every frame shows new phases."""
    return SimulationConfig(width=256, height=256, n_stars=40, n_frames=48, seed=3, flux_min=1e5, flux_max=3e5,
                            camera=CameraModel(gain=4.0), drift_px_per_s=(90.0, 63.0), **psf)


def test_gaussian_psf_estimate_is_zero_and_nothing_changes() -> None:
    """The Gaussian debiasing is exact for a Gaussian PSF, even under-sampled: nothing to calibrate."""
    result = _simulated_errors(_drifting(psf_sigma=0.6), "GAUSSFIT", 40)
    cal = result.calibration
    assert cal.n_stars > 500
    assert abs(cal.estimate_x[0]) < 3 * cal.error_x[0] and abs(cal.estimate_y[0]) < 3 * cal.error_y[0]
    assert not cal.active and result.rms[1] == result.rms[0]


def test_undersampled_moffat_s_curve_is_removed() -> None:
    """A Moffat (beta 1.5, FWHM 0.9 px) is not the Gaussian BICUBIC is debiased with: an S-curve to remove."""
    result = _simulated_errors(_drifting(psf_model="moffat", psf_fwhm=0.9, moffat_beta=1.5), "BICUBIC", 40)
    cal = result.calibration
    assert cal.active and cal.amplitude_x[0] < -0.01
    assert result.s_curve[0] < -0.01 and abs(result.s_curve[1]) < 0.5 * abs(result.s_curve[0])
    assert result.rms[1] < result.rms[0]


def _first_x(path: Path, method: str) -> np.ndarray:
    with LogReader(path) as log:
        message = next(iter(log.messages(topics.centroid_topic(method))))
        return np.array([s["x"] for s in message.payload["stars"]])


def test_centroid_stage_phase_correction_auto_file_and_info(tmp_path: Path) -> None:
    sim, off, auto = tmp_path / "sim.mcap", tmp_path / "off.mcap", tmp_path / "auto.mcap"
    simulate_log(replace(_drifting(psf_sigma=0.6), n_frames=24), sim)
    centroid_log(sim, off, methods="GAUSSFIT")
    summary = centroid_log(sim, auto, methods="GAUSSFIT", phase_correction="auto")
    record = summary.to_dict()["phase_correction"]
    (cal,) = record["calibrations"]
    assert record["source"] == "auto: the stars of the log's first 24 frames" and cal["n_stars"] > 300
    assert cal["amplitude_px"] == {"x": [0.0], "y": [0.0]}  # a Gaussian PSF: no S-curve, nothing changes
    assert np.array_equal(_first_x(auto, "GAUSSFIT"), _first_x(off, "GAUSSFIT"))
    with LogReader(auto) as log:
        assert log.provenance()[-1].parameters["phase_correction"] == record
        assert len(log.metadata(topics.PHASE_METADATA)) == 1
    text = info_text(log_facts(auto))
    assert "pixel-phase correction (auto" in text and "GAUSSFIT" in text
    summary_json = tmp_path / "summary.json"  # what ``starlog centroid --json`` prints
    summary_json.write_text(json.dumps(summary.to_dict()))
    assert load_phase_calibrations(summary_json) == {"GAUSSFIT": PhaseCalibration.from_dict(cal)}
    info_json = tmp_path / "info.json"  # ``starlog info --json`` of the output: its calibration again
    info_json.write_text(json.dumps(log_facts(auto), default=str))
    assert load_phase_calibrations(info_json) == {"GAUSSFIT": PhaseCalibration.from_dict(cal)}
    # a calibration given as a file (here made up), as the JSON of a run prints it
    given = PhaseCalibration("GAUSSFIT", (-0.05,), (-0.03,), (-0.05,), (-0.03,), (0.01,), (0.01,), 400, (True,))
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({"phase_correction": {"calibrations": [given.to_dict()]}}))
    again = tmp_path / "file.mcap"
    result = CliRunner().invoke(cli, ["centroid", str(sim), "-o", str(again), "--method", "GAUSSFIT,MOMENT",
                                      "--phase-correction", str(path), "-q"])
    assert result.exit_code == 0, result.output
    raw = _first_x(off, "GAUSSFIT")
    assert np.allclose(_first_x(again, "GAUSSFIT"), given.apply(raw, raw)[0]) and not np.allclose(_first_x(again, "GAUSSFIT"), raw)
    assert "MOMENT left uncorrected: no calibration for MOMENT" in result.output
    assert "file: " in CliRunner().invoke(cli, ["info", str(again)]).output


def test_centroid_stage_declines_a_static_field_with_few_stars(tmp_path: Path, sim_log: Path) -> None:
    out = tmp_path / "c.mcap"
    summary = centroid_log(sim_log, out, methods="GAUSSFIT", phase_correction="auto")
    record = summary.to_dict()["phase_correction"]
    assert record["calibrations"] == [] and "too few distinct star positions" in record["declined"]["GAUSSFIT"]
    assert not any("left uncorrected" in n for n in summary.notes)  # routine under the default: info shows it
    plain = centroid_log(sim_log, tmp_path / "p.mcap", methods="GAUSSFIT", phase_correction="off")
    assert "phase_correction" not in plain.to_dict()


def test_positions_quantised_to_the_pixel_are_refused_not_folded():
    rng = np.random.default_rng(3)
    x, y = np.rint(rng.uniform(10, 500, 400)), np.rint(rng.uniform(10, 500, 400))
    with pytest.raises(InvalidInputError, match="would fold positions"):
        estimate_phase_calibration(x, y, np.full(400, 0.01), method="NONE")


@pytest.mark.parametrize("amplitude, ok", [(0.15, True), (-0.158, True), (0.16, False), (-0.3, False)])
def test_a_file_amplitude_that_would_fold_positions_is_refused(amplitude, ok):
    record = {"method": "MOMENT", "amplitude_px": {"x": [amplitude], "y": [0.0]}}
    if ok:
        cal = PhaseCalibration.from_dict(record)
        q = np.linspace(-0.5, 0.5, 1001)
        assert np.all(np.diff(cal.apply(q, q)[0]) > 0)
    else:
        with pytest.raises(InvalidInputError, match="would fold positions"):
            PhaseCalibration.from_dict(record)
