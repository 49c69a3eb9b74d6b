"""Platform motion from all stars: the fit, the joint estimate, the stage, its channels and tables."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.compensation import ScoringProtocol, protocol_figures
from starlog.parquet import export_log
from starlog.codecs import load_json_schema
from starlog import topics
from starlog.io.reader import LogReader
from starlog.platform_motion import (
    MotionParameters,
    Observations,
    PlatformModel,
    apply_motion,
    estimate_platform,
    frame_sums,
    solve_motion,
    star_reference,
)
from starlog.sim import Jitter, SimulationConfig, Simulator
from starlog.stages import simulate_log
from starlog.stages.motion import estimate_track_motion, motion_log

CENTRE = np.array([127.5, 95.5])


def _field(rng: np.random.Generator, n_stars: int) -> np.ndarray:
    return np.column_stack([rng.uniform(10, 245, n_stars), rng.uniform(10, 181, n_stars)])


def _observe(static: np.ndarray, motion: MotionParameters, noise: np.ndarray | float = 0.0,
             rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every star in every frame: (frame, star, measured xy) under ``motion`` (one row per frame)."""
    n_frames, n_stars = motion.dx.size, static.shape[0]
    frame = np.repeat(np.arange(n_frames), n_stars)
    star = np.tile(np.arange(n_stars), n_frames)
    xy = apply_motion(motion.take(frame), static[star] - CENTRE) + CENTRE
    if rng is not None:
        xy = xy + rng.normal(size=xy.shape) * np.broadcast_to(noise, (n_stars,))[star][:, None]
    return frame, star, xy


def _motion(n: int, *, translation: bool, roll: bool) -> MotionParameters:
    t = np.arange(n) / 50.0
    zero = np.zeros(n)
    return MotionParameters(dx=0.4 * np.sin(7 * t) + 0.2 if translation else zero,
                            dy=0.3 * np.cos(5 * t) - 0.1 if translation else zero,
                            roll=2e-3 * np.sin(3 * t) + 1e-3 if roll else zero, scale=zero + 1.0)


@pytest.mark.parametrize(("translation", "roll"), [(True, False), (False, True), (True, True)])
def test_known_rigid_motion_of_noise_free_stars_is_recovered(translation: bool, roll: bool) -> None:
    rng = np.random.default_rng(3)
    static = _field(rng, 9)
    truth = _motion(60, translation=translation, roll=roll)
    frame, star, xy = _observe(static, truth)
    # the fit of each frame, static positions known: the motion itself
    w = np.full(frame.size, 1.0 / 0.02**2)
    fitted = solve_motion(frame_sums(frame, static[star] - CENTRE, xy - CENTRE, w, 60), PlatformModel.RIGID,
                          min_stars=3)
    radius = np.max(np.hypot(*(static - CENTRE).T))
    assert np.max(np.abs(fitted.dx - truth.dx)) < 1e-6 and np.max(np.abs(fitted.dy - truth.dy)) < 1e-6
    assert np.max(np.abs(fitted.roll - truth.roll)) * radius < 1e-6
    # the joint estimate (static positions unknown): every star's fitted position is exact, and the
    # motion is the true one up to the constant gauge (a roll offset, then a translation)
    est = estimate_platform(Observations.build(frame, star, xy[:, 0], xy[:, 1], np.full(frame.size, 0.05)),
                            centre=tuple(CENTRE), model="rigid")
    assert est.converged and not est.outlier.any()
    assert np.max(np.abs(est.residual)) < 1e-6
    offset = est.motion.roll - truth.roll
    assert np.ptp(offset) * radius < 1e-6


def test_similarity_fit_recovers_a_scale() -> None:
    rng = np.random.default_rng(4)
    static = _field(rng, 8)
    truth = _motion(20, translation=True, roll=True)
    truth = MotionParameters(truth.dx, truth.dy, truth.roll, 1.0 + 1e-4 * np.arange(20))
    frame, star, xy = _observe(static, truth)
    fitted = solve_motion(frame_sums(frame, static[star] - CENTRE, xy - CENTRE, np.ones(frame.size), 20),
                          PlatformModel.SIMILARITY, min_stars=3)
    assert np.max(np.abs(fitted.scale - truth.scale)) < 1e-9
    assert np.max(np.abs(fitted.dx - truth.dx)) < 1e-6


def test_gross_outlier_is_rejected_and_flagged() -> None:
    rng = np.random.default_rng(5)
    static = _field(rng, 12)
    truth = _motion(200, translation=True, roll=True)
    frame, star, xy = _observe(static, truth, noise=0.02, rng=rng)
    bad = np.flatnonzero((frame == 77) & (star == 4))[0]
    xy[bad] += (3.0, -2.0)
    est = estimate_platform(Observations.build(frame, star, xy[:, 0], xy[:, 1], np.full(frame.size, 0.05)),
                            centre=tuple(CENTRE))
    assert est.outlier[bad] and not est.used[bad]
    assert est.outlier.sum() <= 2  # nothing else but a rare > 5-sigma draw
    assert est.n_used[77] == 11
    assert np.hypot(*est.residual[bad]) > 3.0
    # the frame's motion is not dragged by it (relative to the neighbouring frames)
    step = (est.motion.dx - truth.dx)[76:79]
    assert np.ptp(step) < 0.05


def test_static_positions_converge_with_stars_coming_and_going() -> None:
    rng = np.random.default_rng(6)
    static = _field(rng, 10)
    truth = _motion(400, translation=True, roll=True)
    frame, star, xy = _observe(static, truth, noise=0.02, rng=rng)
    keep = ~((star < 3) & (frame > 250)) & ~((star == 5) & (frame < 120))  # partial coverage
    obs = Observations.build(frame[keep], star[keep], xy[keep, 0], xy[keep, 1], np.full(keep.sum(), 0.05))
    est = estimate_platform(obs, centre=tuple(CENTRE))
    assert est.converged and est.iterations < 50
    # the static field is the true one up to a rigid gauge: every distance between stars is kept
    d_true = np.hypot(*(static[:, None] - static[None]).transpose(2, 0, 1))
    d_est = np.hypot(*(est.static[:, None] - est.static[None]).transpose(2, 0, 1))
    assert np.max(np.abs(d_est - d_true)) < 0.01
    # and the fitted motion averages to zero (the gauge)
    assert abs(np.mean(est.motion.dx)) < 1e-6 and abs(np.mean(est.motion.roll)) < 1e-9
    assert np.allclose(est.star_noise, 0.02, rtol=0.15)


def test_frames_with_fewer_than_three_stars_have_no_motion() -> None:
    rng = np.random.default_rng(7)
    static = _field(rng, 5)
    frame, star, xy = _observe(static, _motion(30, translation=True, roll=False), noise=0.01, rng=rng)
    keep = ~((frame >= 10) & (frame < 15) & (star >= 2))  # frames 10-14: two stars
    obs = Observations.build(frame[keep], star[keep], xy[keep, 0], xy[keep, 1], np.full(keep.sum(), 0.05))
    est = estimate_platform(obs, centre=tuple(CENTRE), model="translation")
    assert np.array_equal(np.flatnonzero(~est.valid), np.arange(10, 15))
    assert np.isnan(est.residual[(obs.frame >= 10) & (obs.frame < 15)]).all()


def test_simulator_roll_turns_the_field_about_the_image_centre() -> None:
    config = SimulationConfig(width=64, height=48, n_stars=4, n_frames=8, fps=10.0, roll_amplitude_rad=0.01,
                              roll_frequency_hz=1.0, jitter=(Jitter(2.0, 0.1),), margin=8.0, seed=1)
    sim = Simulator(config)
    for n in (0, 3, 7):
        frame = sim.render(n)
        roll = 0.01 * np.sin(2 * np.pi * n / 10.0)
        p = MotionParameters(*(np.full(4, v) for v in (frame.platform_dx, frame.platform_dy, roll, 1.0)))
        expected = apply_motion(p, np.column_stack([sim.field.x, sim.field.y]) - (31.5, 23.5)) + (31.5, 23.5)
        assert frame.platform_roll == pytest.approx(roll)
        assert np.allclose(np.column_stack([frame.x, frame.y]), expected, atol=1e-12)


# ---------------------------------------------------------------- the stage, on a simulated log
@pytest.fixture(scope="module")
def motion_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """simulate (8 stars at least 19 px apart, jitter and roll) → centroid NONE → track STATIC → motion (CLI)."""
    d = tmp_path_factory.mktemp("motion")
    logs = {name: d / f"{name}.mcap" for name in ("sim", "cen", "trk", "mot")}
    config = SimulationConfig(width=128, height=96, n_stars=8, n_frames=240, fps=100.0, margin=12.0, seed=1,
                              flux_min=20_000.0, flux_max=60_000.0, jitter=(Jitter(9.0, 0.08),),
                              roll_amplitude_rad=2e-3, roll_frequency_hz=3.0)
    simulate_log(config, logs["sim"])
    runner = CliRunner()
    for args in (["centroid", str(logs["sim"]), "-o", str(logs["cen"]), "--method", "NONE"],
                 ["track", str(logs["cen"]), "-o", str(logs["trk"]), "--centroids", "NONE", "--model", "STATIC",
                  "--set", "sigma_floor=0.1"],
                 ["motion", str(logs["trk"]), "-o", str(logs["mot"])]):
        result = runner.invoke(cli, [*args, "--workers", "1", "-q"])
        assert result.exit_code == 0, result.output
    return logs


def test_motion_channels_validate_and_round_trip_through_export(motion_logs: dict[str, Path],
                                                               tmp_path: Path) -> None:
    counts = {}
    with LogReader(motion_logs["mot"]) as log:
        assert log.provenance()[-1].stage == "motion"
        for topic, name in ((topics.platform_topic("NONE", "STATIC"), "starlog.PlatformMotion"),
                            (topics.residuals_topic("NONE", "STATIC"), "starlog.StarResiduals")):
            channel = log.channel(topic)
            assert channel.schema_name == name
            assert (channel.schema_encoding, channel.message_encoding) == ("protobuf", "protobuf")
            validator = jsonschema.Draft202012Validator(load_json_schema(name))
            counts[name] = [m.payload for m in log.messages(topic)]
            for payload in counts[name]:  # the dict readers get is the JSON an earlier version wrote
                validator.validate(payload)
    written = export_log(motion_logs["mot"], tmp_path, tables=["motion", "residuals"])
    platform, residuals = counts["starlog.PlatformMotion"], counts["starlog.StarResiduals"]
    assert written == {"motion": len(platform), "residuals": sum(len(m["stars"]) for m in residuals)}
    table = pq.read_table(tmp_path / "motion.parquet").to_pylist()
    assert [r["dx"] for r in table] == [m["dx"] for m in platform]
    assert {"log_time", "frame", "method", "model", "dx", "dy", "roll", "sigma_dx", "sigma_dy", "sigma_roll",
            "n_stars", "residual_rms"} <= set(table[0])
    rows = pq.read_table(tmp_path / "residuals.parquet").to_pylist()
    assert [r["residual_x"] for r in rows] == [s["residual_x"] for m in residuals for s in m["stars"]]


def test_motion_follows_the_simulated_platform(motion_logs: dict[str, Path]) -> None:
    with LogReader(motion_logs["mot"]) as log:
        platform = [m.payload for m in log.messages(topics.platform_topic("NONE", "STATIC"))]
        truth = [m.payload for m in log.messages(topics.TRUTH)]
    assert len(platform) == len(truth)
    for key, true_key, tol in (("dx", "platform_dx", 3.0), ("roll", "platform_roll", 3.0)):
        est = np.array([p[key] for p in platform])
        ref = np.array([t[true_key] for t in truth])
        err = (est - est.mean()) - (ref - ref.mean())
        sigma = np.median([p["sigma_" + key] for p in platform])
        assert np.sqrt(np.mean(err**2)) < tol * sigma  # within the fit's own 1-sigma (a few times)


def test_relative_error_matches_the_truth_series_error_of_raw_centroids(motion_logs: dict[str, Path]) -> None:
    with LogReader(motion_logs["trk"]) as log:
        data, est = estimate_track_motion(log, "/track/NONE/STATIC")
        truth = [m.payload["stars"] for m in log.messages(topics.TRUTH)]
    static = np.array([(s["x_static"], s["y_static"]) for s in truth[0]])
    positions = np.array([[(s["x"], s["y"]) for s in stars] for stars in truth])
    for slot in np.flatnonzero(est.star_eligible):
        rows = np.flatnonzero(data.obs.star == slot)
        meas = data.obs.xy[rows]
        star_id = int(np.argmin(np.hypot(*(static - meas.mean(axis=0)).T)))
        reference, variance = star_reference(data.obs, est, slot, data.obs.frame[rows])
        relative = protocol_figures(meas, protocol=ScoringProtocol.RELATIVE, relative=reference,
                                    relative_variance=variance, truth_series=positions[data.obs.frame[rows], star_id])
        by_name = {f.reference: f.rmse_before for f in relative}
        assert by_name["relative"] == pytest.approx(by_name["truth_series"], rel=0.15)


def test_motion_cli_json_and_summary(motion_logs: dict[str, Path], tmp_path: Path) -> None:
    result = CliRunner().invoke(cli, ["motion", str(motion_logs["trk"]), "-o", str(tmp_path / "m.mcap"), "--model",
                                      "translation", "--json", "-q"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    channel = summary["channels"]["/track/NONE/STATIC"]
    assert summary["fit"] == "translation" and channel["frames_with_motion"] == channel["frames"] == 240
    assert channel["stars"] == 8 and len(channel["star_noise"]) == 8
    with pytest.raises(Exception, match="unknown motion option"):
        motion_log(motion_logs["trk"], tmp_path / "x.mcap", options={"k_sgima": 3})


# ---------------------------------------------------------------- compensate: relative protocol, motion modes
def test_separate_on_a_motionless_field_equals_keep_within_noise() -> None:
    from starlog.compensation import evaluate

    rng = np.random.default_rng(8)
    static = _field(rng, 10)
    still = MotionParameters(*(np.zeros(400) for _ in range(3)), np.ones(400))
    frame, star, xy = _observe(static, still, noise=0.03, rng=rng)
    obs = Observations.build(frame, star, xy[:, 0], xy[:, 1], np.full(frame.size, 0.05))
    est = estimate_platform(obs, centre=tuple(CENTRE))
    reference, variance = star_reference(obs, est, 0, np.arange(400))
    series = xy[star == 0]
    common = dict(rate_hz=50.0, protocol="truth", truth_fixed=static[0], truth_series=np.tile(static[0], (400, 1)),
                  static_position=est.static[0], platform_displacement=reference - est.static[0],
                  reference_variance=variance)
    keep = evaluate(series, motion="keep", **common)
    separate = evaluate(series, motion="separate", **common)
    noise = float(np.sqrt(np.mean(variance)))  # the other stars' motion estimate, added back by separate
    assert keep.motion == "keep" and separate.motion == "separate"
    assert separate.figure("truth_fixed").rmse_after == pytest.approx(keep.figure("truth_fixed").rmse_after,
                                                                      abs=2 * noise)
    assert np.sqrt(np.mean(np.sum((separate.compensated - keep.compensated) ** 2, axis=1))) < 3 * noise + 0.01
    with pytest.raises(Exception, match="platform displacement"):
        evaluate(series, rate_hz=50.0, protocol="relative")


@pytest.fixture(scope="module")
def compensated_log(motion_logs: dict[str, Path]) -> Path:
    out = motion_logs["trk"].with_name("cmp.mcap")
    result = CliRunner().invoke(cli, ["compensate", str(motion_logs["trk"]), "-o", str(out), "--rate", "25,50",
                                      "--protocol", "truth,relative", "--motion", "keep,separate", "-q"])
    assert result.exit_code == 0, result.output
    return out


def test_compensate_relative_and_separate_records_channels_and_tables(compensated_log: Path, tmp_path: Path) -> None:
    with LogReader(compensated_log) as log:
        records = [m.payload for m in log.messages("/compensated/NONE/STATIC/decisions")]
        assert {"/compensated/NONE/STATIC/50Hz/relative", "/compensated/NONE/STATIC/50Hz/relative/separate",
                "/compensated/NONE/STATIC/25Hz/truth/separate"} <= set(log.topics)
        validators: dict[int, jsonschema.Draft202012Validator] = {}
        for schema, _, message in log.raw_messages([t for t in log.topics if t.startswith("/compensated")]):
            assert schema is not None
            validators.setdefault(schema.id, jsonschema.Draft202012Validator(json.loads(schema.data)))
            validators[schema.id].validate(json.loads(message.data))
    assert [(r["rate_hz"], r["protocol"], r["motion"]) for r in records] == [
        (rate, protocol, motion) for rate in (25.0, 50.0) for protocol in ("truth", "relative")
        for motion in ("keep", "separate")]
    for r in records:
        figures = {f["reference"]: f for f in r["figures"]}
        if r["motion"] == "separate":  # the jitter is kept: the error against the moving truth drops
            assert figures["truth_series"]["effective"] > 0.3
        if r["protocol"] == "relative":
            assert [f["reference"] for f in r["figures"]][0] == "relative"
            for key in ("rmse_before", "rmse_after"):
                assert figures["relative"][key] == pytest.approx(figures["truth_series"][key], rel=0.25)
    export_log(compensated_log, tmp_path, tables=["compensation", "decisions"])
    samples = pq.read_table(tmp_path / "compensation.parquet").to_pylist()
    assert {(r["protocol"], r["motion"]) for r in samples} == {(p, m) for p in ("truth", "relative")
                                                               for m in ("keep", "separate")}
    assert {r["motion"] for r in pq.read_table(tmp_path / "decisions.parquet").to_pylist()} == {"keep", "separate"}


# ---------------------------------------------------------------- the regime map (experiment --sweep)
def test_regime_map_configs_tables_and_plot(tmp_path: Path) -> None:
    from starlog.report.experiment_figures import plot_regime_map
    from starlog.experiment.regime import (
        FIGURES,
        RATES,
        REGIME_FIELDS,
        median_gains,
        regime_configs,
        regime_markdown,
        write_regime_parquet,
    )

    specs = regime_configs(0.01, quick=False)
    assert {(s["stars"], s["jitter_ratio"]) for s in specs} == {(n, r) for n in (3, 6, 20)
                                                                 for r in (0.0, 0.5, 1.0, 2.0, 5.0, 10.0)}
    for spec in specs:
        config = SimulationConfig.from_dict(spec["config"])
        rms = np.sqrt(sum(j.amplitude_px**2 / 2 for j in config.jitter))
        assert rms == pytest.approx(spec["jitter_ratio"] * 0.01)
        assert spec["sigma_floor"] >= 2 * rms
    rows = [{"stars": n, "jitter_ratio": r, "jitter_rms_px": r * 0.01, "noise_px": 0.01, "model": "STATIC",
             "rate_hz": rate, "motion": motion, "protocol": protocol, "reference": reference, "n_scored": 60,
             "rmse_before": 0.02, "rmse_after": 0.01, "effective": 0.5 if motion == "keep" else -0.25}
            for n in (3, 20) for r in (0.0, 2.0) for rate in (10.0, 50.0) for motion in ("keep", "separate")
            for protocol, reference in (("truth", "truth_series"), ("truth", "truth_fixed"),
                                        ("leakfree", "heldout_mean"), ("relative", "relative"))]
    table = pq.read_table(write_regime_parquet(rows, tmp_path / "r.parquet"))
    assert table.schema.names == list(REGIME_FIELDS) and table.num_rows == len(rows)
    text = regime_markdown(rows)
    assert "## relative / relative, 50 Hz" in text and "| 20 | 50 % / -25 % | 50 % / -25 % |" in text
    assert plot_regime_map(rows, median_gains(rows), FIGURES, RATES, tmp_path / "r.png").stat().st_size > 1000


def test_experiment_sweep_flag_reaches_the_command(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    seen: list[bool] = []

    class Summary:
        def text(self) -> str:
            return "map"

    def experiment_command(output: Path, **options: object) -> Summary:
        seen.append(bool(options["sweep"]))
        return Summary()

    monkeypatch.setattr("starlog.experiment.experiment_command", experiment_command)
    for flags in ([], ["--sweep"]):
        assert CliRunner().invoke(cli, ["experiment", "-o", str(tmp_path), *flags, "-q"]).exit_code == 0
    assert seen == [False, True]
