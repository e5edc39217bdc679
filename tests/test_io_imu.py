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
