"""Fault injection on the sidewalk's data files: malformed files (binary, NUL bytes, NaN, inf,
missing columns, words, empty) are named by the loader and by the command line."""

from __future__ import annotations

import numpy as np
import pytest
from faults_helpers import ROOT, _one_line_error

from mpcpearl_jax.envs.sidewalk.loader import DataFormatError, load_eth_ucy

ZARA = ROOT.parent / "shared" / "data" / "crowds_zara01.txt"


BAD_DATA = {
    "binary.bin": bytes(range(256)) * 8,
    "nul.txt": b"0 1 2.0 3.0\n\x00\x00\x00\n",
    "nan.txt": b"0 1 2.0 3.0\n10 1 nan 3.0\n",
    "inf.txt": b"0 1 2.0 inf\n",
    "columns.txt": b"0 1 2.0\n",
    "words.txt": b"frame ped x y\n",
    "empty.txt": b"\n# only a comment\n",
    # a 29.1 TiB allocation of windows, and an int64 overflow into a nonsense span
    "frame-1e15.txt": b"0 1 2.0 3.0\n10 1 2.0 3.0\n1e15 1 2.0 3.0\n",
    "frame-1e30.txt": b"0 1 2.0 3.0\n10 1 2.0 3.0\n1e30 1 2.0 3.0\n",
    "id-1e30.txt": b"0 1e30 2.0 3.0\n10 1 2.0 3.0\n",
}


@pytest.mark.parametrize("name", sorted(BAD_DATA))
def test_malformed_data_files_are_named(tmp_path, capsys, name):
    path = tmp_path / name
    path.write_bytes(BAD_DATA[name])
    with pytest.raises(DataFormatError, match=str(path)):
        load_eth_ucy(path)
    argv = ["--preset", "smoke", "--data", str(path), "--out", str(tmp_path / "r")]
    line = _one_line_error(capsys, argv, env="sidewalk", online_eval=True, mpc={"v_max": None})
    assert str(path) in line and not (tmp_path / "r").exists()  # not even a folder with .lock


@pytest.mark.skipif(not ZARA.is_file(), reason="UCY Zara 01 not in ../shared/data")
def test_real_data_file_still_loads():
    scene = load_eth_ucy(ZARA)
    assert scene.num_pedestrians > 100 and np.all(np.isfinite(scene.xy))
