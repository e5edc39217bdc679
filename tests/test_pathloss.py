"""The path-loss prior of the radio map (hybridloc/radio/pathloss.py)."""

import numpy as np
import pytest

from hybridloc.radio.pathloss import HEIGHT_M, fit_path_loss


def _simulate(rng, a, p0, n, shadow_db=4.0, r50=-88.0, s50=2.5, n_scans=600):
    """Scans along two corridors of a 60 x 30 m floor; each transmitter heard with the logistic detection
    law around its log-distance mean, shadowed by ``shadow_db``."""
    x = rng.uniform(0, 60, n_scans)
    y = np.where(rng.random(n_scans) < 0.5, 5.0, 25.0) + rng.normal(0, 0.3, n_scans)
    pos = np.column_stack([x, y])
    r_scan, r_col, r_val = [], [], []
    for j in range(len(p0)):
        d2 = ((pos - a[j]) ** 2).sum(1) + HEIGHT_M**2
        mu = p0[j] - 5.0 * n[j] * np.log10(d2)
        r = mu + rng.normal(0, shadow_db, n_scans)
        heard = rng.random(n_scans) < 1.0 / (1.0 + np.exp(-(mu - r50) / s50))
        r_scan += np.flatnonzero(heard).tolist()
        r_col += [j] * int(heard.sum())
        r_val += r[heard].tolist()
    return pos, np.array(r_scan), np.array(r_col), np.array(r_val)


def test_fit_recovers_transmitters_and_detection():
    rng = np.random.default_rng(7)
    m = 6
    a = np.column_stack([rng.uniform(5, 55, m), rng.uniform(5, 25, m)])
    p0 = rng.uniform(-45, -30, m)
    n = rng.uniform(2.2, 3.5, m)
    pos, r_scan, r_col, r_val = _simulate(rng, a, p0, n)
    pl = fit_path_loss(pos, r_scan, r_col, r_val, m)
    assert pl.ok.all()
    # hundreds of readings 4 dB apart: the position to within a few metres (a 4 dB error is the distance
    # changing by 10^(4 / (10 n)) ~ x1.35 at 10 m), the fitted model's mean along the corridors within
    # the shadowing's standard error; the residual spread is the shadowing
    assert np.median(np.linalg.norm(pl.a - a, axis=1)) < 4.0
    d2 = ((pos[:, None, :] - a[None]) ** 2).sum(-1) + HEIGHT_M**2
    truth = p0[None] - 5.0 * n[None] * np.log10(d2)
    strong = truth > -85.0
    assert np.median(np.abs(pl.mean(pos) - truth)[strong]) < 2.0
    assert np.median(pl.resid_sd) == pytest.approx(4.0, abs=1.0)
    # the detection law: its 50 % point within a couple of dB, its scale positive and a few dB
    assert pl.r50 == pytest.approx(-88.0, abs=3.0)
    assert 0.5 < pl.s50 < 6.0


def test_too_few_readings_are_not_fitted():
    rng = np.random.default_rng(1)
    pos = rng.uniform(0, 10, (5, 2))
    pl = fit_path_loss(pos, np.arange(5), np.zeros(5, int), np.full(5, -60.0), 2)
    assert not pl.ok.any()
    # no fitted transmitter: the detection law falls back to its a-priori values
    assert np.isfinite(pl.r50) and pl.s50 > 0


def test_radio_map_prior_option():
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.radio.survey import LabelledScan
    from hybridloc.types import RfScan, Technology

    rng = np.random.default_rng(3)
    m = 4
    a = np.array([[10.0, 5.0], [50.0, 25.0], [30.0, 15.0], [55.0, 5.0]])
    pos, r_scan, r_col, r_val = _simulate(rng, a, np.full(m, -35.0), np.full(m, 2.8), n_scans=300)
    scans = []
    for i in range(len(pos)):
        sel = r_scan == i
        if sel.any():
            rssi = {f"ap{int(j)}": float(v) for j, v in zip(r_col[sel], r_val[sel])}
            scans.append(LabelledScan(RfScan(float(i), Technology.WIFI, rssi), pos[i].copy(), 0.5, "F1"))
    plain = build_radio_map(scans)
    pl = build_radio_map(scans, params=BuildParams(prior="path-loss", reach_m=40.0))
    # the path-loss map reaches farther from the corridors than the kernel does (no plan here: the grid
    # spans the data plus the larger of the margin and the reach), and between the corridors, 10 m from
    # both, it predicts the transmitter in the middle (at (30, 15)) as the strongest
    fp, fk = pl.floors["F1"], plain.floors["F1"]
    assert len(fp.cells) > len(fk.cells)
    mid = int(np.argmin(np.linalg.norm(fp.cells - [30.0, 15.0], axis=1)))
    assert np.linalg.norm(fk.cells - [30.0, 15.0], axis=1).min() > 2.0  # the kernel map has no cell there
    assert int(np.argmax(fp.mu[mid])) == int(np.flatnonzero(fp.tx == pl.tx_index["ap2"])[0])
    with pytest.raises(ValueError, match="prior"):
        build_radio_map(scans, params=BuildParams(prior="nonsense"))
    with pytest.raises(ValueError, match="reach_m"):
        build_radio_map(scans, params=BuildParams(prior="path-loss", reach_m=0.0))


def test_map_files_stay_readable_both_ways(tmp_path):
    """A map built with the default parameters is the file older hybridloc wrote (no new header keys),
    and a header with parameters this version does not know still loads."""
    import json

    from hybridloc.radio.radiomap import BuildParams, RadioMap, build_radio_map
    from hybridloc.radio.survey import LabelledScan
    from hybridloc.types import RfScan, Technology

    rng = np.random.default_rng(5)
    pos, r_scan, r_col, r_val = _simulate(rng, np.array([[10.0, 5.0], [40.0, 25.0]]), np.full(2, -35.0), np.full(2, 2.8), n_scans=120)
    scans = [
        LabelledScan(
            RfScan(float(i), Technology.WIFI, {f"ap{int(j)}": float(v) for j, v in zip(r_col[r_scan == i], r_val[r_scan == i])}),
            pos[i].copy(),
            0.5,
            "F1",
        )
        for i in range(len(pos))
        if (r_scan == i).any()
    ]
    build_radio_map(scans).save(tmp_path / "d.npz")
    with np.load(tmp_path / "d.npz") as z:
        meta = json.loads(bytes(z["meta"]).decode())
    assert "prior" not in meta["params"] and "reach_m" not in meta["params"]
    build_radio_map(scans, params=BuildParams(prior="path-loss", reach_m=12.0)).save(tmp_path / "p.npz")
    with np.load(tmp_path / "p.npz") as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["meta"]).decode())
    assert meta["params"]["prior"] == "path-loss"
    meta["params"]["a_later_setting"] = 3
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(tmp_path / "later.npz", **arrays)
    m = RadioMap.load(tmp_path / "later.npz")
    assert m.params.prior == "path-loss" and m.params.reach_m == 12.0


def test_degenerate_readings_are_not_fitted():
    """Readings from one spot, a NaN reading and a floor where every pair is heard: no transmitter is
    placed from what cannot place it, nothing is NaN, and the detection law keeps its a-priori values."""
    from hybridloc.radio.pathloss import R50_PRIOR, S50_PRIOR

    rng = np.random.default_rng(2)
    spot = np.repeat([[3.0, 4.0], [3.5, 4.0]], 10, axis=0)  # 20 readings from two spots 0.5 m apart
    pl = fit_path_loss(spot, np.arange(20), np.zeros(20, int), rng.normal(-60, 3, 20), 1)
    assert not pl.ok.any()
    pos = np.column_stack([rng.uniform(0, 40, 50), rng.uniform(0, 10, 50)])
    val = -40.0 - 25.0 * np.log10(np.hypot(pos[:, 0] - 20, pos[:, 1] - 5) + 1.0)
    pl = fit_path_loss(pos, np.arange(50), np.zeros(50, int), val, 1)
    assert pl.ok.all()
    # every (scan, transmitter) pair heard: no detection law can be fitted
    assert (pl.r50, pl.s50) == (R50_PRIOR, S50_PRIOR)
    val[7] = np.nan  # a NaN reading is left out, not spread over the floor
    pl = fit_path_loss(pos, np.arange(50), np.zeros(50, int), val, 1)
    assert pl.ok.all() and np.isfinite(pl.p0).all() and np.isfinite(pl.resid_sd).all()
    assert np.isfinite([pl.r50, pl.s50]).all() and pl.s50 > 0


def test_map_build_with_the_path_loss_prior_on_the_bundled_sample(tmp_path):
    """``map build --prior path-loss --reach R`` end to end: the map file keeps the prior in its build
    parameters, reaches farther than the kernel's map over the same walks, and a bad reach is refused."""
    import subprocess
    import sys

    from hybridloc.radio.radiomap import RadioMap
    from hybridloc.samples import ILC_SITE1_F1

    traces = sorted((ILC_SITE1_F1 / "F1" / "path_data_files").glob("*.txt.gz"))[:12]
    run = lambda *a: subprocess.run([sys.executable, "-m", "hybridloc.cli", *a], capture_output=True, text=True, timeout=300)  # noqa: E731
    r = run("map", "build", "--format", "msft", *map(str, traces), "--out", str(tmp_path / "k.npz"))
    assert r.returncode == 0, r.stderr
    r = run("map", "build", "--format", "msft", *map(str, traces), "--out", str(tmp_path / "p.npz"), "--prior", "path-loss", "--reach", "20")
    assert r.returncode == 0, r.stderr
    k, p = RadioMap.load(tmp_path / "k.npz"), RadioMap.load(tmp_path / "p.npz")
    assert p.params.prior == "path-loss" and p.params.reach_m == 20.0
    assert sum(len(f.cells) for f in p.floors.values()) > sum(len(f.cells) for f in k.floors.values())
    for f in p.floors.values():
        assert np.isfinite(f.mu).all() and np.isfinite(f.sd).all() and ((f.pd > 0) & (f.pd < 1)).all()
    r = run("map", "build", "--format", "msft", *map(str, traces), "--out", str(tmp_path / "x.npz"), "--prior", "path-loss", "--reach", "-1")
    assert r.returncode == 2 and "--reach" in r.stderr
    r = run("map", "build", "--format", "msft", *map(str, traces), "--out", str(tmp_path / "x.npz"), "--reach", "20")
    assert r.returncode == 2 and "--prior path-loss" in r.stderr
