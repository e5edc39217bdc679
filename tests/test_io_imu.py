import numpy as np
import pytest

from hybridloc.io import detect_format
from hybridloc.io.common import DataFormatError
from hybridloc.io.imu_files import read_imu_csv, read_openshoe_mat, read_pyshoe_mat, write_imu_csv
from hybridloc.types import ImuBlock
from hybridloc.units import G0


def _imu(n=100, rate=100.0, mag=True):
    t = np.arange(n) / rate
    acc = np.tile([0.0, 0.0, G0], (n, 1)) + 0.01 * np.sin(t)[:, None]
    gyr = np.tile([0.01, -0.02, 0.3], (n, 1))
    m = np.tile([20e-6, 0.0, -40e-6], (n, 1)) if mag else None
    return ImuBlock(t, acc, gyr, m)


def test_csv_round_trip(tmp_path):
    p = tmp_path / "imu.csv"
    blk = _imu()
    write_imu_csv(p, blk)
    assert detect_format(p) == "csv"
    rec = read_imu_csv(p)
    np.testing.assert_allclose(rec.imu.accel_body, blk.accel_body, rtol=1e-8)
    np.testing.assert_allclose(rec.imu.mag_body, blk.mag_body, rtol=1e-8)
    assert rec.report.ok


def test_csv_in_g_is_refused_then_read_with_option(tmp_path):
    p = tmp_path / "g.csv"
    lines = ["t,ax,ay,az,gx,gy,gz"] + [f"{i * 0.01:.2f},0,0,1.0,0,0,0.1" for i in range(50)]
    p.write_text("\n".join(lines))
    with pytest.raises(DataFormatError, match="looks like g"):
        read_imu_csv(p)
    rec = read_imu_csv(p, accel_unit="g")
    assert rec.imu.accel_body[0, 2] == pytest.approx(G0)


def test_csv_gyro_in_degrees_is_refused(tmp_path):
    p = tmp_path / "d.csv"
    lines = ["t,ax,ay,az,gx,gy,gz"] + [f"{i * 0.01:.2f},0,0,9.8,0,0,{300 if i == 10 else 5}" for i in range(50)]
    p.write_text("\n".join(lines))
    with pytest.raises(DataFormatError, match="deg/s"):
        read_imu_csv(p)


def test_csv_bad_rows_reported(tmp_path):
    p = tmp_path / "b.csv"
    rows = [f"{i * 0.01:.2f},0,0,9.8,0,0,0" for i in range(30)]
    rows[5] = "0.05,0,0,nan,0,0,0"
    rows[6] = "0.06,0,0,9.8,0,0"
    rows[7] = "0.07,x,0,9.8,0,0,0"
    rows.append("0.10,0,0,9.8,0,0,0")  # backwards in time -> duplicate of t=0.10 after sorting
    p.write_text("t,ax,ay,az,gx,gy,gz\n" + "\n".join(rows))
    rec = read_imu_csv(p)
    assert rec.report.counts["non-finite"] == 1 and rec.report.counts["malformed-line"] == 2
    assert rec.report.notes["out-of-order"] == 1 and rec.report.notes["duplicate-timestamp"] == 1
    assert len(rec.imu) == 27
    with pytest.raises(DataFormatError, match=r"b.csv:7: non-finite"):
        read_imu_csv(p, on_error="raise")


def test_csv_wrong_header(tmp_path):
    p = tmp_path / "h.csv"
    p.write_text("time,a,b\n1,2,3\n")
    with pytest.raises(DataFormatError, match="header"):
        read_imu_csv(p)


@pytest.mark.shared_data
def test_every_pyshoe_trial_loads(pyshoe_dir):
    files = sorted(pyshoe_dir.glob("*.mat"))
    assert len(files) == 28
    for f in files:
        assert detect_format(f) == "pyshoe"
        rec = read_pyshoe_mat(f)
        assert rec.report.ok
        assert rec.rate_hz == pytest.approx(200.0, rel=0.01)  # the dataset's 200 Hz
        assert rec.truth is not None and len(rec.truth) == len(rec.imu)
        assert rec.extras["trial_error"].shape == (5,)
        assert np.all(rec.extras["trial_error"] > 0)
        # Specific force magnitude at the first (standing) samples is about g.
        assert np.linalg.norm(rec.imu.accel_body[:50].mean(0)) == pytest.approx(G0, rel=0.05)


@pytest.mark.shared_data
def test_openshoe_loads(shared_data):
    f = shared_data / "openshoe" / "square2.mat"
    assert detect_format(f) == "openshoe"
    rec = read_openshoe_mat(f)
    assert len(rec.imu) == 8687 and rec.imu.duration == pytest.approx(86.86)
    assert np.linalg.norm(rec.imu.accel_body[:100].mean(0)) == pytest.approx(G0, rel=0.01)


def test_corrupt_mat_is_a_clear_error(tmp_path):
    p = tmp_path / "x.mat"
    p.write_bytes(b"MATLAB 5.0 MAT-file" + b"\x00" * 50)
    with pytest.raises(DataFormatError):
        read_pyshoe_mat(p)


# ------------------------------------------------------------------ SensorConnect (gait-driven set)
_SC_HEADER = "Time," + ",".join(
    f"inertial-1.2:{c}" for c in ("scaledAccelX", "scaledAccelY", "scaledAccelZ", "scaledGyroX", "scaledGyroY", "scaledGyroZ")
)


def _sc_file(tmp_path, rows, header=_SC_HEADER):
    p = tmp_path / "SensorConnectData_1.csv"
    p.write_text(header + "\n" + "\n".join(",".join(f"{v:.9g}" for v in r) for r in rows) + "\n")
    return p


def test_sensorconnect_reads_g_as_si_and_refuses_the_wrong_units(tmp_path):
    from hybridloc.io.imu_files import read_sensorconnect_csv

    n = 400
    t = np.arange(n) / 200.0
    rows = [[ti, 0.0, 0.0, -1.0, 0.01, 0.0, 0.0] for ti in t]  # at rest, z down: -1 g
    rows.insert(10, [t[10], float("nan"), 0.0, -1.0, 0.0, 0.0, 0.0])  # a NaN row: counted, not read
    rec = read_sensorconnect_csv(_sc_file(tmp_path, rows))
    assert len(rec.imu) == n
    assert np.allclose(np.linalg.norm(rec.imu.accel_body, axis=1), G0, rtol=1e-6)  # g -> m/s^2
    assert np.allclose(rec.imu.gyro_body[:, 0], 0.01)  # rad/s as written
    assert detect_format(_sc_file(tmp_path, rows)) is not None
    # the same file already in m/s^2 under a "scaled" (g) name: refused with the reason, not scaled twice
    rows_si = [[r[0], r[1], r[2], r[3] * G0, *r[4:]] for r in rows if np.isfinite(r[1])]
    with pytest.raises(DataFormatError, match="in g"):
        read_sensorconnect_csv(_sc_file(tmp_path, rows_si))
    with pytest.raises(DataFormatError):
        read_sensorconnect_csv(_sc_file(tmp_path, rows, header="Time,a,b,c,d,e,f"))


def test_sensorconnect_bunched_host_stamps_are_respaced(tmp_path):
    from hybridloc.io.imu_files import read_sensorconnect_csv

    # stamps arriving in pairs every 10 ms (a 200 Hz stream read by the host): re-spaced evenly
    t = np.repeat(np.arange(250) * 0.010, 2) + np.tile(np.arange(2) * 1e-6, 250)
    rec = read_sensorconnect_csv(_sc_file(tmp_path, [[ti, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0] for ti in t]))
    assert rec.extras["retimed"]
    dt = np.diff(rec.imu.t)
    assert np.allclose(dt, dt.mean(), rtol=1e-9) and abs(1.0 / dt.mean() - 200.0) < 2.0
    # with a real gap (a lost second) the stamps are kept, and the reason reported
    t_gap = np.concatenate([t, t[-1] + 1.0 + t])
    rec = read_sensorconnect_csv(_sc_file(tmp_path, [[ti, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0] for ti in t_gap]))
    assert not rec.extras["retimed"] and np.allclose(rec.imu.t, t_gap, rtol=0, atol=1e-8)
    assert rec.report.counts["bunched-timestamps"] == 1


def test_sensorconnect_real_trials_and_their_footprints(shared_data):
    from hybridloc.io.imu_files import footprints_beside, read_sensorconnect_csv

    files = sorted((shared_data / "gait-driven-own").glob("SensorConnectData_*.csv.gz"))
    if not files:
        pytest.skip("gait-driven-own is absent from ../shared/data")
    rec = read_sensorconnect_csv(files[0])
    imu = rec.imu
    # a foot at rest reads 1 g (+-2 % for a MEMS unit's scale and bias), at a steady rate
    still = np.linalg.norm(imu.gyro_body, axis=1) < 0.05
    assert still.sum() > 50
    assert abs(np.median(np.linalg.norm(imu.accel_body[still], axis=1)) - G0) < 0.02 * G0
    assert np.all(np.diff(imu.t) > 0)
    fp = footprints_beside(files[0])
    assert fp is not None and fp.pos_xy.shape[1] == 2 and fp.stride[0] == 0
    # a walk of fp.n_strides strides of 0.5-2 m each (walking to running)
    assert 0.3 * fp.n_strides < fp.distance_m < 2.5 * fp.n_strides


def test_sensorconnect_clipped_rate_is_told_though_it_never_repeats(shared_data):
    """Walk 35 runs: its 3DM-GX5-25 clips the pitch rate at a ceiling its readings wander about
    (never an exact repeat). The foot INS counts those samples as saturated (each within 1 % of the
    axis's extreme, in several swings); walk 32, whose largest rate stays below the ceiling, has none."""
    from hybridloc.ins.foot import PLATEAU_ACCEL, PLATEAU_GYRO
    from hybridloc.ins.stance import stance_runs
    from hybridloc.io.imu_files import read_sensorconnect_csv

    d = shared_data / "gait-driven-own"
    if not (d / "SensorConnectData_35.csv.gz").exists():
        pytest.skip("gait-driven-own is absent from ../shared/data")
    imu = read_sensorconnect_csv(d / "SensorConnectData_35.csv.gz").imu
    _, sg = imu.saturated(PLATEAU_ACCEL, PLATEAU_GYRO)
    g = imu.gyro_body
    assert len(stance_runs(sg)[0]) >= 3
    near = (g[sg] >= 0.99 * g.max(axis=0)) | (g[sg] <= 0.99 * g.min(axis=0))
    assert near.any(axis=1).all()
    # not one reading up there repeats its predecessor: the exact-repeat test alone would miss them
    assert not np.any((g[1:] == g[:-1]) & (np.abs(g[1:]) >= PLATEAU_GYRO))
    imu32 = read_sensorconnect_csv(d / "SensorConnectData_32.csv.gz").imu
    assert not imu32.saturated(PLATEAU_ACCEL, PLATEAU_GYRO)[1].any()
