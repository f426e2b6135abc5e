from pathlib import Path

import numpy as np
import pytest

from ardflow.ardcore.data import (SILVERBOX_SPLITS, Dataset, load_pendulum, load_silverbox, read_dataset)
from ardflow.ardcore.errors import DataError

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"


def write(tmp_path, text, name="d.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def good_rows(n=20):
    return "\n".join(f"{0.1 * i},{np.sin(i)},{i}" for i in range(n))


def test_reads_csv_with_nan_in_observed(tmp_path):
    p = write(tmp_path, "t,y,u\n" + good_rows() + "\n")
    text = p.read_text().splitlines()
    text[3] = "0.2,,2"
    p.write_text("\n".join(text))
    ds = read_dataset(p)
    assert len(ds) == 20 and np.isnan(ds.columns["y"][2])
    t, Y, U = ds.arrays(["y"], ["u"])
    assert Y.shape == (20, 1) and U.shape == (20, 1)


@pytest.mark.parametrize("text,msg", [
    ("", "empty file"),
    ("t,y\n", "no data rows"),
    ("t,y\n0,1\n0.1,2\n", "too few points"),
    ("t,y\n" + "\n".join(f"{0.1 * i},1" for i in range(12)) + "\n0.5,1\n", "not strictly increasing at row 13 \\(t=0.5 after t=1.1"),
    ("t,y\n" + "\n".join(f"{0.1 * i},{'inf' if i == 4 else 1}" for i in range(12)), "infinite value at row 5"),
    ("t,y\n" + "\n".join(f"{0.1 * i},{'abc' if i == 4 else 1}" for i in range(12)), "'abc' is not a number"),
    ("t,y\n" + "\n".join(f"{'nan' if i == 4 else 0.1 * i},1" for i in range(12)), "time is not finite"),
    ("y,u\n" + "\n".join(f"{i},1" for i in range(12)), "no time column 't'"),
    ("1,2\n" + "\n".join(f"{i},1" for i in range(12)), "header"),
])
def test_bad_files_have_clear_messages(tmp_path, text, msg):
    with pytest.raises(DataError, match=msg):
        read_dataset(write(tmp_path, text))


def test_missing_and_unknown_columns(tmp_path):
    p = write(tmp_path, "t,y,u\n" + good_rows())
    with pytest.raises(DataError, match="unknown column 'q'"):
        read_dataset(p, columns=["y", "q"])
    ds = read_dataset(p)
    with pytest.raises(DataError, match="missing column 'z'"):
        ds.arrays(["z"], [])


def test_nan_in_input_column_is_rejected(tmp_path):
    rows = good_rows().splitlines()
    rows[5] = "0.5,0.1,"
    ds = read_dataset(write(tmp_path, "t,y,u\n" + "\n".join(rows)))
    with pytest.raises(DataError, match="input column 'u' has NaN at row 6"):
        ds.arrays(["y"], ["u"])


def test_npz_roundtrip(tmp_path):
    t = np.arange(30) * 0.1
    np.savez(tmp_path / "d.npz", t=t, y=np.cos(t))
    ds = read_dataset(tmp_path / "d.npz")
    assert np.array_equal(ds.t, t)
    ds.to_csv(tmp_path / "back.csv")
    assert np.array_equal(read_dataset(tmp_path / "back.csv").columns["y"], np.cos(t))


@pytest.mark.skipif(not (SHARED / "SNLS80mV.csv").exists(), reason="shared data not present")
def test_silverbox_loads_through_the_same_path():
    ds = load_silverbox(SHARED / "SNLS80mV.csv")
    assert len(ds) == 131072 and set(ds.columns) == {"u", "y"}
    assert ds.t[1] == pytest.approx(1 / 610.3515625)
    a, b = SILVERBOX_SPLITS["estimation"]
    est = ds.slice(a, b)
    assert len(est) == b - a and np.isfinite(est.columns["y"]).all()


@pytest.mark.skipif(not (SHARED / "pendulum" / "adip_pend_data.mat").exists(), reason="shared data not present")
def test_pendulum_mat_loads():
    ds = load_pendulum(SHARED / "pendulum" / "adip_pend_data.mat")
    assert set(ds.columns) == {"y"}
    assert ds.t[0] == pytest.approx(0.061, abs=1e-6) and ds.t[-1] == pytest.approx(120, abs=0.01)
    assert 1.1 < np.max(ds.columns["y"]) < 1.4


def test_dataset_validates_direct_construction():
    with pytest.raises(DataError, match="has 3 values for 12 times"):
        Dataset(np.arange(12.0), {"y": np.zeros(3)})
