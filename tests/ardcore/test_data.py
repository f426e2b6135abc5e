from pathlib import Path

import numpy as np
import pytest

from ardflow.ardcore.data import (SILVERBOX_SPLITS, Dataset, load_pendulum, load_silverbox, read_dataset)
from ardflow.ardcore.errors import DataError



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


def test_silverbox_ships_with_its_checksum_and_splits():
    ds = load_silverbox()
    assert len(ds) == 131072 and set(ds.columns) == {"u", "y"}
    assert ds.t[1] == pytest.approx(1 / 610.3515625)
    assert ds.meta["units"]["y"] == "V"
    a, b = SILVERBOX_SPLITS["estimation"]
    est = ds.slice(a, b)
    assert len(est) == b - a and np.isfinite(est.columns["y"]).all()


def test_a_damaged_silverbox_copy_is_refused(tmp_path, monkeypatch):
    import gzip

    import ardflow.ardcore.data as data

    raw = bytearray(gzip.decompress(data.silverbox_path().read_bytes()))
    raw[100] = ord("9") if raw[100] != ord("9") else ord("8")  # one digit changed
    bad = tmp_path / "SNLS80mV.csv.gz"
    bad.write_bytes(gzip.compress(bytes(raw)))
    monkeypatch.setattr(data, "silverbox_path", lambda: bad)
    with pytest.raises(DataError, match="checksum"):
        data.load_silverbox()


def test_truncated_gzip_csv_is_a_data_error(tmp_path):
    p = tmp_path / "d.csv.gz"
    p.write_bytes(b"\x1f\x8b\x08\x00garbage")
    with pytest.raises(DataError, match="gzip"):
        read_dataset(p)


def test_pendulum_reads_from_ardflow_data(tmp_path, monkeypatch):
    from tests.pendulum_standin import pendulum_folder

    monkeypatch.delenv("ARDFLOW_DATA", raising=False)
    with pytest.raises(DataError, match="ARDFLOW_DATA"):
        load_pendulum()
    monkeypatch.setenv("ARDFLOW_DATA", str(pendulum_folder(tmp_path)))
    ds = load_pendulum()
    assert set(ds.columns) == {"y"}
    assert ds.t[0] == pytest.approx(0.061, abs=1e-6) and ds.t[-1] == pytest.approx(120, abs=0.01)
    assert 1.1 < np.max(ds.columns["y"]) < 1.4


def test_spec_paths_fall_back_to_ardflow_data(tmp_path, monkeypatch):
    from ardflow.ardcore.selection.spec import load_spec
    from tests.pendulum_standin import pendulum_folder

    spec_file = Path(__file__).resolve().parents[2] / "examples" / "pendulum_diagnose.json"
    monkeypatch.setenv("ARDFLOW_DATA", str(tmp_path / "empty"))
    with pytest.raises(DataError, match="ARDFLOW_DATA"):
        load_spec(spec_file).data.load(spec_file.parent)
    monkeypatch.setenv("ARDFLOW_DATA", str(pendulum_folder(tmp_path)))
    ds = load_spec(spec_file).data.load(spec_file.parent)
    assert len(ds) == (40000 - 2000) // 20


def test_dataset_validates_direct_construction():
    with pytest.raises(DataError, match="has 3 values for 12 times"):
        Dataset(np.arange(12.0), {"y": np.zeros(3)})


def test_reports_label_axes_with_the_specs_names_and_units():
    from ardflow.ardcore.selection.spec import DataSpec

    d = DataSpec(path="x.csv", units={"t": "s", "y": "V"}, labels={"y": "output voltage"})
    assert (d.axis_label("y"), d.axis_label("t"), d.axis_label("u")) == ("output voltage y [V]", "time [s]", "u")
    # the reference problem's generated record keeps its own names; another record never borrows them
    assert DataSpec(generator="reference").axis_label("y") == "pitch angle theta [rad]"
    assert "theta" not in DataSpec(path="x.csv").axis_label("y")
