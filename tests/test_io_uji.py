import numpy as np
import pytest

from hybridloc.io import detect_format
from hybridloc.io.common import DataFormatError
from hybridloc.io.uji import read_uji

HEADER = "WAP001,WAP002,WAP003,LONGITUDE,LATITUDE,FLOOR,BUILDINGID,SPACEID,RELATIVEPOSITION,USERID,PHONEID,TIMESTAMP"


def test_sentinel_and_bad_rows(tmp_path):
    p = tmp_path / "u.csv"
    p.write_text(
        "\n".join(
            [
                HEADER,
                "-60,100,-80,-7500.5,4864900.1,2,1,106,2,2,23,1371713733",
                "100,100,100,-7501.0,4864901.0,0,0,1,1,1,1,1371713734",
                "-60,200,-80,-7500.5,4864900.1,2,1,106,2,2,23,1371713733",  # 200 dBm: not valid
                "-60,-70,-80,-7500.5,4864900.1,2,1,106",  # short
                "-60,-70,x,-7500.5,4864900.1,2,1,106,2,2,23,1371713733",
            ]
        )
    )
    assert detect_format(p) == "ujiindoorloc"
    d = read_uji(p)
    assert len(d) == 2
    assert np.isnan(d.rssi_dbm[0, 1]) and d.rssi_dbm[0, 0] == -60
    assert dict(d.scan(0).rssi_dbm) == {"WAP001": -60.0, "WAP003": -80.0}
    assert d.report.counts == {"rssi-out-of-range": 1, "malformed-line": 2}
    with pytest.raises(DataFormatError, match=r"u.csv:4: rssi-out-of-range"):
        read_uji(p, on_error="raise")


def test_not_uji(tmp_path):
    p = tmp_path / "n.csv"
    p.write_text("WAP001,FOO\n1,2\n")
    with pytest.raises(DataFormatError, match="UJIIndoorLoc"):
        read_uji(p)


@pytest.mark.shared_data
def test_real_training_file(shared_data):
    d = read_uji(shared_data / "ujiindoorloc" / "trainingData.csv.gz")
    assert len(d) == 19937 and len(d.waps) == 520 and d.report.ok
    assert set(d.building.tolist()) == {0, 1, 2}
    assert d.floor.min() == 0 and d.floor.max() == 4
    det = d.rssi_dbm[np.isfinite(d.rssi_dbm)]
    assert det.min() >= -104 and det.max() <= 0  # the dataset's documented range is -104..0 dBm
