"""Empirical PSF (ePSF), PSFFIT, the Moffat / Airy simulator PSFs and their Cramer-Rao bound."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from starlog import topics
from click.testing import CliRunner
from numpy.testing import assert_allclose

from starlog.centroiding import CentroidFlag, centroid_crb, measure_centroids
from starlog.centroiding.crb import centroid_crb_psf
from starlog.centroiding.epsf import (
    EPSF,
    GaussianPSF,
    build_epsf,
    epsf_from_frames,
    gaussian_epsf,
    symmetric_below,
)
from starlog.cli import cli
from starlog.detect import detect_stars
from starlog.errors import InvalidInputError
from starlog.facts import log_facts
from starlog.cli.describe import info_text
from starlog.io.reader import LogReader
from starlog.sim import CameraModel, SimulationConfig, Simulator
from starlog.sim.profiles import AiryPSF, MoffatPSF, render_profile_stars
from starlog.sim.psf import render_stars
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log

PEDESTAL = 120.0


def _grid_field(rng: np.random.Generator, n: int = 8, step: int = 30) -> tuple[np.ndarray, np.ndarray]:
    g = 20 + step * np.arange(n)
    cx, cy = np.meshgrid(g, g)
    return cx.ravel() + rng.uniform(-0.5, 0.5, cx.size), cy.ravel() + rng.uniform(-0.5, 0.5, cy.size)


def _frames(render, n_frames: int, seed: int, flux: float = 3e4, shape=(250, 250)):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_frames):
        x, y = _grid_field(rng)
        img = CameraModel().expose(20.0 + render(shape, x, y, np.full(x.size, flux)), rng)
        out.append((img, detect_stars(img)))
    return out


def test_epsf_of_gaussian_stars_matches_the_pixel_integrated_gaussian() -> None:
    sigma = 1.2
    frames = _frames(lambda s, x, y, f: render_stars(s, x, y, f, sigma), 3, seed=1)
    epsf = epsf_from_frames(frames, psf_sigma=1.4, half_size=7)  # starts 17 % too wide
    ref = gaussian_epsf(sigma, epsf.half_size, epsf.oversampling)
    assert epsf.n_stars > 150 and epsf.oversampling == 4 and epsf.half_size == 8
    assert np.abs(epsf.data - ref.data).max() < 0.03 * ref.data.max()
    assert epsf.fwhm == pytest.approx(ref.fwhm, rel=0.02)
    assert epsf.data.sum() / 16 == pytest.approx(1.0)


def test_epsf_agrees_with_photutils_epsfbuilder() -> None:
    """Oracle: photutils' EPSFBuilder on the same stars gives the same profile (within noise)."""
    photutils_psf = pytest.importorskip("photutils.psf")
    from astropy.nddata import NDData
    from astropy.table import Table

    sigma = 1.2
    frames = _frames(lambda s, x, y, f: render_stars(s, x, y, f, sigma), 1, seed=2)
    img, det = frames[0]
    ours = epsf_from_frames(frames, psf_sigma=sigma, half_size=7)
    data = img.astype(np.float64) - np.median(det["background"])
    stars = photutils_psf.extract_stars(NDData(data=data), Table({"x": det["x"], "y": det["y"]}), size=17)
    builder = photutils_psf.EPSFBuilder(oversampling=4, maxiters=5, progress_bar=False)
    theirs, _ = builder(stars)
    t = theirs.data / theirs.data.sum() * 16
    c, k = (t.shape[0] - 1) // 2, (ours.data.shape[0] - 1) // 2
    prof_t = t[c, c - 12:c + 13]
    prof_o = ours.data[k, k - 12:k + 13]
    assert np.abs(prof_t - prof_o).max() < 0.05 * prof_o.max()


def test_epsf_metadata_round_trip_and_pickle() -> None:
    epsf = EPSF(gaussian_epsf(1.1, 6, 4).data, 4, n_stars=17)
    back = EPSF.from_metadata(epsf.to_metadata())
    assert_allclose(back.data, epsf.data, rtol=0, atol=0)
    assert back.n_stars == 17 and back.oversampling == 4 and back.fwhm == pytest.approx(epsf.fwhm)
    clone = pickle.loads(pickle.dumps(epsf))
    u = np.arange(-4.0, 5.0)
    assert_allclose(clone.evaluate_grid(u, np.array([0.2]), np.array([-0.3]))[0],
                    epsf.evaluate_grid(u, np.array([0.2]), np.array([-0.3]))[0])
    with pytest.raises(InvalidInputError):
        EPSF(np.zeros((10, 10)), 4)


def test_epsf_interpolation_matches_the_analytic_model() -> None:
    epsf, exact = gaussian_epsf(1.0, 8, 4), GaussianPSF(1.0)
    rng = np.random.default_rng(0)
    u = np.arange(-6.0, 7.0)
    cx, cy = rng.uniform(-0.7, 0.7, 30), rng.uniform(-0.7, 0.7, 30)
    grid = epsf.evaluate_grid(u, cx, cy, deriv=True)
    general = epsf.evaluate(u[None, None, :] - cx[:, None, None], u[None, :, None] - cy[:, None, None], deriv=True)
    analytic = exact.evaluate_grid(u, cx, cy, deriv=True)
    for a, b, c in zip(grid, general, analytic):
        assert_allclose(a, b, rtol=0, atol=1e-12)
        assert_allclose(a, c, rtol=0, atol=1e-4)


@pytest.mark.parametrize("with_epsf", [False, True])
def test_psffit_recovers_noise_free_positions(with_epsf: bool) -> None:
    sigma = 1.2
    ph = np.linspace(-0.5, 0.5, 6)
    px, py = np.meshgrid(ph, ph)
    cx, cy = np.meshgrid(30 + 40 * np.arange(6), 30 + 40 * np.arange(6))
    x, y = (cx + px).ravel(), (cy + py).ravel()
    img = PEDESTAL + render_stars((260, 260), x, y, np.full(x.size, 2e4), sigma)
    det = detect_stars(img)
    epsf = gaussian_epsf(sigma, 7, 4) if with_epsf else None
    c = measure_centroids(img, det, method="PSFFIT", psf_sigma=sigma, epsf=epsf)
    k = np.hypot(c["x"][:, None] - x[None, :], c["y"][:, None] - y[None, :]).argmin(axis=1)
    tol = 2e-3 if with_epsf else 1e-6
    assert_allclose(c["x"], x[k], rtol=0, atol=tol)
    assert_allclose(c["y"], y[k], rtol=0, atol=tol)
    assert not np.any(c["flags"] & CentroidFlag.FIT_FAILED)
    assert_allclose(c["flux"], 2e4, rtol=2e-3)


def test_psffit_on_noisy_moffat_stars_with_their_epsf() -> None:
    """A log's ePSF of Moffat stars: PSFFIT near the Moffat bound, its sigma calibrated."""
    psf = MoffatPSF(fwhm=2.8, beta=2.5)
    render = lambda s, x, y, f: render_profile_stars(s, x, y, f, psf)  # noqa: E731
    epsf = epsf_from_frames(_frames(render, 4, seed=5), psf_sigma=1.3, half_size=6)
    rng = np.random.default_rng(6)
    x, y = _grid_field(rng)
    flux = 2e4
    expected = 20.0 + render((250, 250), x, y, np.full(x.size, flux))
    errs, zs = [], []
    for _ in range(8):
        img = CameraModel().expose(expected, rng)
        det = detect_stars(img)
        c = measure_centroids(img, det, method="PSFFIT", gain=1.0, read_noise=3.0, psf_sigma=1.3, epsf=epsf)
        k = np.hypot(c["x"][:, None] - x[None, :], c["y"][:, None] - y[None, :]).argmin(axis=1)
        e = np.concatenate([c["x"] - x[k], c["y"] - y[k]])
        errs.append(e)
        zs.append(e / np.concatenate([c["sigma"], c["sigma"]]))
    rmse = float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))
    bound = centroid_crb_psf(flux=flux, pixel_psf=psf.pixel_values, sky=20.0, read_noise=3.0, x_phase=0.25)
    assert rmse < 1.15 * bound
    assert 0.8 < float(np.sqrt(np.mean(np.concatenate(zs) ** 2))) < 1.25


def test_build_epsf_without_precise_stars_keeps_the_starting_gaussian() -> None:
    frames = _frames(lambda s, x, y, f: render_stars(s, x, y, f, 1.5), 1, seed=3, flux=400.0)
    epsf = epsf_from_frames(frames, psf_sigma=1.5, half_size=6)
    assert epsf.n_stars == 0
    assert_allclose(epsf.data, gaussian_epsf(1.5, 7, 4).data, rtol=0, atol=1e-6)
    with pytest.raises(InvalidInputError):
        epsf_from_frames([(np.zeros((40, 40)), detect_stars(np.zeros((40, 40))))], psf_sigma=1.0, half_size=4)
    with pytest.raises(InvalidInputError):
        build_epsf(*_empty_stamps(), psf_sigma=1.0)


def _empty_stamps():
    from starlog.centroiding.stamps import gather_stamps

    z = np.zeros(0)
    return gather_stamps(np.zeros((20, 20)), z, z, 3, z, z, 1.0, np.inf), z, z, z


@pytest.mark.parametrize("psf", [MoffatPSF(fwhm=2.8, beta=2.5), MoffatPSF(fwhm=2.0, beta=4.0)], ids=str)
def test_moffat_flux_sums_to_the_given_flux(psf: MoffatPSF) -> None:
    img = render_profile_stars((401, 401), [200.3], [199.8], [1e4], psf)
    assert img.sum() == pytest.approx(1e4, rel=2e-5)
    # the FWHM is the one asked for: half the peak intensity at r = FWHM / 2
    assert psf.intensity(np.array((psf.fwhm / 2) ** 2)) == pytest.approx(0.5 * psf.intensity(np.array(0.0)))


def test_airy_keeps_all_but_its_far_rings() -> None:
    psf = AiryPSF(lambda_d=1.5)
    img = render_profile_stars((301, 301), [150.0], [150.0], [1e4], psf)
    assert 0.985 * 1e4 < img.sum() < 1e4
    # first dark ring at 1.22 lambda/D
    assert psf.intensity(np.array((1.2197 * 1.5) ** 2)) < 1e-6 * psf.intensity(np.array(0.0))


def test_crb_of_a_pixel_psf_matches_the_gaussian_bound() -> None:
    g = GaussianPSF(1.2)
    a = centroid_crb(flux=5e3, psf_sigma=1.2, sky=20.0, read_noise=3.0, x_phase=0.3, y_phase=-0.1)
    b = centroid_crb_psf(flux=5e3, pixel_psf=lambda dx, dy: g.evaluate(dx, dy)[0], sky=20.0, read_noise=3.0,
                         x_phase=0.3, y_phase=-0.1)
    assert b == pytest.approx(a, rel=1e-5)


def test_simulator_psf_models_and_their_provenance() -> None:
    base = dict(width=64, height=64, n_stars=2, n_frames=1, margin=20.0, seed=4)
    gauss = SimulationConfig(**base)
    assert "psf_model" not in gauss.to_dict() and gauss.psf_profile() is None
    moffat = SimulationConfig(**base, psf_model="moffat", moffat_beta=3.0)
    assert SimulationConfig.from_dict(moffat.to_dict()) == moffat
    profile = moffat.psf_profile()
    assert isinstance(profile, MoffatPSF) and profile.beta == 3.0
    assert profile.fwhm == pytest.approx(2.3548 * 1.2, rel=1e-4)
    sim = Simulator(moffat)
    expected, _, _ = sim.expected_electrons(0)
    assert (expected - moffat.sky).sum() == pytest.approx(sim.field.flux.sum(), rel=2e-3)
    airy = SimulationConfig(**base, psf_model="airy", airy_lambda_d=2.0)
    assert airy.psf_profile() == AiryPSF(lambda_d=2.0)
    with pytest.raises(ValueError):
        SimulationConfig(**base, psf_model="lorentz")


def test_centroid_psf_empirical_end_to_end(tmp_path: Path) -> None:
    sim = tmp_path / "sim.mcap"
    config = SimulationConfig(width=160, height=160, n_stars=16, n_frames=12, seed=9, margin=15.0,
                              flux_min=2e4, flux_max=6e4, psf_model="moffat", psf_fwhm=3.0)
    simulate_log(config, sim)
    out = tmp_path / "cen.mcap"
    summary = centroid_log(sim, out, methods="PSFFIT,GAUSSFIT", psf="empirical")
    assert summary.epsf is not None and summary.epsf["n_stars"] > 0 and summary.to_dict()["epsf"] == summary.epsf
    with LogReader(out) as log:
        (_, meta), = log.metadata(topics.EPSF_METADATA)
        epsf = EPSF.from_metadata(meta)
        record = log.provenance()[-1]
        truth = {m.payload["frame"]: m.payload for m in log.messages("/sim/truth")}
        errs = {}
        for method in ("PSFFIT", "GAUSSFIT"):
            e = []
            for message in log.messages(f"/stars/centroids/{method}"):
                body = message.payload
                tx = np.array([s["x"] for s in truth[body["frame"]]["stars"]])
                ty = np.array([s["y"] for s in truth[body["frame"]]["stars"]])
                for s in body["stars"]:
                    k = int(np.argmin(np.hypot(tx - s["x"], ty - s["y"])))
                    e += [s["x"] - tx[k], s["y"] - ty[k]]
            errs[method] = float(np.sqrt(np.mean(np.square(e))))
    assert epsf.fwhm == pytest.approx(summary.epsf["fwhm_px"], rel=1e-3)
    assert epsf.fwhm == pytest.approx(3.0, rel=0.1)  # the Moffat's FWHM, widened a little by the pixel
    assert record.parameters["psf"] == "empirical" and record.parameters["epsf"]["n_stars"] == epsf.n_stars
    assert errs["PSFFIT"] < 0.05
    info = log_facts(out)
    assert info["epsf"][0]["oversampling"] == 4
    assert "epsf" in info_text(info) and "oversampling 4" in info_text(info)


def test_cli_centroid_psf_empirical_and_info(tmp_path: Path) -> None:
    runner = CliRunner()
    sim, cen = tmp_path / "s.mcap", tmp_path / "c.mcap"
    result = runner.invoke(cli, ["simulate", "-o", str(sim), "--size", "96x96", "--stars", "6", "--frames", "6",
                                 "--flux", "20000:50000", "--psf", "airy", "--airy-zero", "3", "-q"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(cli, ["centroid", str(sim), "-o", str(cen), "--method", "PSFFIT", "--psf", "empirical",
                                 "-q", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output[result.output.index("{"):])["epsf"]["oversampling"] == 4
    text = runner.invoke(cli, ["info", str(cen)]).output
    assert "epsf" in text and "FWHM" in text
    params = log_facts(sim)["provenance"][0]["parameters"]
    assert params["psf_model"] == "airy" and params["airy_lambda_d"] == pytest.approx(3 / 1.2196698912665045)


def test_psffit_with_gaussian_psf_needs_no_epsf(sim_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "g.mcap"
    summary = centroid_log(sim_log, out, methods="PSFFIT", psf="gaussian")
    assert summary.epsf is None and "epsf" not in summary.to_dict()
    with LogReader(out) as log:
        assert log.metadata(topics.EPSF_METADATA) == []
    with pytest.raises(ValueError):
        centroid_log(sim_log, tmp_path / "x.mcap", methods="PSFFIT", psf="moffat")


def test_an_epsf_from_fewer_stars_than_its_phase_cells_stays_the_gaussian_and_from_few_is_symmetric() -> None:
    moffat = MoffatPSF(fwhm=2.8, beta=2.5)
    frames = _frames(lambda s, x, y, f: render_profile_stars(s, x, y, f, moffat), 1, seed=5)
    img, det = frames[0]
    few = epsf_from_frames([(img, det[:10])], psf_sigma=1.2, half_size=6)  # 10 stars < 4 x 4 phase cells
    assert few.n_stars == 0 and np.array_equal(few.data, gaussian_epsf(1.2, 7, 4).data)
    some = epsf_from_frames([(img, det[:24])], psf_sigma=1.2, half_size=6)  # 16 <= 24 < 2 x 16: point-symmetric
    assert 16 <= some.n_stars < symmetric_below(4)
    assert_allclose(some.data, some.data[::-1, ::-1], rtol=0, atol=1e-12)
    # it keeps the Moffat's wings, which the Gaussian of the same core does not have
    wing = some.data[some.data.shape[0] // 2, -8]
    assert wing > 3 * gaussian_epsf(1.2, 7, 4).data[some.data.shape[0] // 2, -8]
    full = epsf_from_frames(frames, psf_sigma=1.2, half_size=6)
    assert full.n_stars >= symmetric_below(4) and not np.allclose(full.data, full.data[::-1, ::-1], atol=1e-9)
