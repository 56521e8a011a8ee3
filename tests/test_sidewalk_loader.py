"""ETH/UCY loading, windowing, interpolation and the sidewalk task splits (method §4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mpcpearl_jax.envs import make_tasks
from mpcpearl_jax.envs.sidewalk import (
    SIDEWALK_CONFIG,
    DataFormatError,
    full_window_starts,
    interpolate_track,
    load_eth_ucy,
    select_longest,
    split_indices,
    task_windows,
    window_starts,
    window_tracks,
)

ZARA = Path(__file__).resolve().parents[2] / "shared" / "data" / "crowds_zara01.txt"
needs_zara = pytest.mark.skipif(not ZARA.is_file(), reason=f"UCY Zara 01 data not found at {ZARA}")
T, DT = SIDEWALK_CONFIG.horizon, SIDEWALK_CONFIG.dt


def _write(tmp_path, text, name="scene.txt"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _rows(frames, ped, x0, vx, y=3.0):
    return "".join(
        f"{f:.1f}\t{ped:.1f}\t{x0 + vx * (f - frames[0]) / 25:.6f}\t{y}\n" for f in frames
    )


# ------------------------------------------------------------------------------ Zara 01
@needs_zara
def test_zara_scene_numbers():
    scene = load_eth_ucy(ZARA)
    assert scene.num_pedestrians == 148
    assert scene.span_seconds == pytest.approx(360.4)
    assert scene.frame_step == 10
    assert len(window_starts(scene, T, DT)) == 36
    full = full_window_starts(scene, T, DT)
    assert len(full) == 31
    # the 5 windows set aside contain the three annotation holes
    holes = [(2420, 2520), (2810, 2870), (8190, 8360)]
    dropped = sorted(set(window_starts(scene, T, DT)) - set(full))
    for s in dropped:
        assert any(a < s + 250 and b > s for a, b in holes)


@needs_zara
def test_zara_splits_are_25_train_6_test_and_deterministic():
    train = make_tasks("sidewalk", "train", data=ZARA)
    test = make_tasks("sidewalk", "test", data=str(ZARA))
    assert train.human_pos.shape == (25, T + 1, 5, 2)
    assert test.human_mask.shape == (6, T + 1, 5)
    np.testing.assert_allclose(
        task_windows("test", ZARA, SIDEWALK_CONFIG), [20, 70, 150, 200, 250, 300]
    )
    starts_train = task_windows("train", ZARA, SIDEWALK_CONFIG)
    assert not set(starts_train) & {20.0, 70.0, 150.0, 200.0, 250.0, 300.0}
    again = make_tasks("sidewalk", "test", seed=7, data=ZARA)  # seed does not matter with data
    np.testing.assert_array_equal(np.asarray(again.human_pos), np.asarray(test.human_pos))
    ood = make_tasks("sidewalk", "ood", data=ZARA)
    assert ood.human_pos.shape[0] == 5


@needs_zara
def test_zara_window_is_np_interp_of_raw_rows_for_the_longest_five():
    """Rebuild one test window straight from np.loadtxt and np.interp."""
    raw = np.loadtxt(ZARA)
    start = 70.0 * 25  # the second test window, frames 1750..2000
    grid = start + np.arange(T + 1)
    tracks = {}
    for ped in np.unique(raw[:, 1]):
        rows = raw[raw[:, 1] == ped]
        rows = rows[np.argsort(rows[:, 0])]
        present = (grid >= rows[0, 0]) & (grid <= rows[-1, 0])
        if present.any():
            xy = np.stack([np.interp(grid, rows[:, 0], rows[:, k]) for k in (2, 3)], axis=-1)
            tracks[int(ped)] = (present.sum(), xy, present)
    order = sorted(tracks, key=lambda p: (-tracks[p][0], p))[:5]
    task = make_tasks("sidewalk", "test", data=ZARA)
    pos, mask = np.asarray(task.human_pos[1]), np.asarray(task.human_mask[1])
    for slot, ped in enumerate(order):
        _, xy, present = tracks[ped]
        np.testing.assert_array_equal(mask[:, slot], present)
        np.testing.assert_allclose(pos[present, slot], xy[present], atol=1e-5)
    assert mask.sum(axis=0).tolist() == sorted(mask.sum(axis=0).tolist(), reverse=True)


# ------------------------------------------------------------------------ malformed files
def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.txt"
    with pytest.raises(FileNotFoundError, match="nowhere.txt"):
        load_eth_ucy(path)
    with pytest.raises(FileNotFoundError, match="nowhere.txt"):
        make_tasks("sidewalk", "train", data=path)


def test_wrong_column_count_names_file_and_line(tmp_path):
    path = _write(tmp_path, "0\t1\t2.0\t3.0\n10\t1\t2.5\t3.0\n20\t1\t3.0\n", "cols.txt")
    with pytest.raises(DataFormatError, match=r"cols\.txt: line 3: expected 4 columns.*got 3"):
        load_eth_ucy(path)


def test_non_numeric_value_names_file_and_line(tmp_path):
    path = _write(tmp_path, "0 1 2.0 3.0\n\n10 1 abc 3.0\n", "text.txt")
    with pytest.raises(DataFormatError, match=r"text\.txt: line 3: non-numeric value 'abc'"):
        load_eth_ucy(path)


@pytest.mark.parametrize("frame", ["1e15", "1e30", "-100000001"])
def test_a_frame_beyond_any_video_names_file_and_line(tmp_path, frame):
    """A frame of 1e15 made the windows a 29.1 TiB allocation; 1e30 overflowed int64."""
    path = _write(tmp_path, f"0 1 2.0 3.0\n10 1 2.5 3.0\n{frame} 1 3.0 3.0\n", "far.txt")
    with pytest.raises(DataFormatError, match=rf"far\.txt: line 3: frame {frame} is beyond"):
        load_eth_ucy(path)
    ok = _write(tmp_path, "0 1 2.0 3.0\n100000000 1 3.0 3.0\n", "edge.txt")
    assert load_eth_ucy(ok).frame.max() == 10**8


def test_non_finite_value_is_rejected(tmp_path):
    path = _write(tmp_path, "0 1 2.0 3.0\n10 1 nan 3.0\n", "nan.txt")
    with pytest.raises(DataFormatError, match=r"nan\.txt: line 2: non-finite"):
        load_eth_ucy(path)


@pytest.mark.parametrize("text", ["", "\n\n  \n", "# a comment only\n"])
def test_empty_scene(tmp_path, text):
    path = _write(tmp_path, text, "empty.txt")
    with pytest.raises(DataFormatError, match=r"empty\.txt: empty scene"):
        load_eth_ucy(path)


def test_duplicate_rows_are_rejected(tmp_path):
    path = _write(tmp_path, "0 1 2.0 3.0\n0 1 2.1 3.0\n", "dup.txt")
    with pytest.raises(DataFormatError, match=r"dup\.txt: pedestrian 1 has two rows for frame 0"):
        load_eth_ucy(path)


def test_scene_shorter_than_a_window(tmp_path):
    path = _write(tmp_path, _rows(range(0, 200, 10), 1, 1.0, 1.0), "short.txt")
    with pytest.raises(ValueError, match=r"short\.txt: no 'train' windows of 10 s"):
        make_tasks("sidewalk", "train", data=path)


# ------------------------------------------------------------------- windowing on a toy file
def test_windows_with_holes_are_not_full(tmp_path):
    # person 1 walks frames 0..760 except for a hole 520..560 where nobody is annotated
    frames = [f for f in range(0, 770, 10) if not 520 <= f <= 560]
    scene = load_eth_ucy(_write(tmp_path, _rows(frames, 1, 0.5, 1.2)))
    np.testing.assert_array_equal(window_starts(scene, T, DT), [0, 250, 500])
    np.testing.assert_array_equal(full_window_starts(scene, T, DT), [0, 250])
    ids, pos, mask = window_tracks(scene, 500.0, T, DT)
    # inside the track's own hole the person is absent (no interpolation across it)
    # (samples at frames 500, 510, then 570..760)
    assert mask[:11, 0].all() and not mask[11:70, 0].any() and mask[70:, 0].all()


def test_interpolation_matches_np_interp_inside_span_only():
    rng = np.random.default_rng(0)
    frames = np.arange(40.0, 200.0, 10.0)
    xy = rng.normal(size=(frames.size, 2))
    query = np.arange(0.0, 251.0)
    pos, present = interpolate_track(frames, xy, query, max_gap=10.0)
    inside = (query >= 40) & (query <= 190)
    np.testing.assert_array_equal(present, inside)
    for k in range(2):
        np.testing.assert_allclose(pos[inside, k], np.interp(query[inside], frames, xy[:, k]))
    # outside the span the nearest end is held (finite, never extrapolated)
    np.testing.assert_allclose(pos[query < 40], np.broadcast_to(xy[0], (40, 2)))
    np.testing.assert_allclose(pos[query > 190], np.broadcast_to(xy[-1], ((query > 190).sum(), 2)))


def test_window_tracks_interpolate_at_dt(tmp_path):
    # two people, one entering mid-window; positions linear in time
    text = _rows(range(0, 260, 10), 1, 1.0, 1.0) + _rows(range(100, 260, 10), 2, 14.0, -1.5, 4.0)
    scene = load_eth_ucy(_write(tmp_path, text))
    ids, pos, mask = window_tracks(scene, 0.0, T, DT)
    assert ids.tolist() == [1, 2]
    t = DT * np.arange(T + 1)
    np.testing.assert_allclose(pos[:, 0, 0], 1.0 + t, atol=1e-9)
    np.testing.assert_array_equal(mask[:, 1], np.arange(T + 1) >= 100)
    np.testing.assert_allclose(pos[100:, 1, 0], 14.0 - 1.5 * (t[100:] - 4.0), atol=1e-9)


def test_select_longest_orders_breaks_ties_and_pads():
    steps = 6
    mask = np.zeros((steps, 4), bool)
    mask[:2, 0] = True  # id 30: 2 steps
    mask[:5, 1] = True  # id 10: 5 steps
    mask[1:3, 2] = True  # id 20: 2 steps (tie with 30, smaller id first)
    pos = np.arange(steps * 4 * 2, dtype=float).reshape(steps, 4, 2)
    ids = np.array([30, 10, 20, 40])  # id 40 never present
    out_ids, out_pos, out_mask = select_longest(ids, pos, mask, 3, (-5.0, -5.0))
    assert out_ids.tolist() == [10, 20, 30]
    np.testing.assert_array_equal(out_pos[:, 0], pos[:, 1])
    padded = select_longest(ids[:1], pos[:, :1], mask[:, :1], 3, (-5.0, -5.0))
    assert padded[0].tolist() == [30, -1, -1]
    assert not padded[2][:, 1:].any() and np.all(padded[1][:, 1:] == -5.0)


def test_split_indices_every_fifth_from_the_third():
    split = split_indices(31)
    assert split["test"].tolist() == [2, 7, 12, 17, 22, 27]
    assert len(split["train"]) == 25
    assert sorted(split["train"].tolist() + split["test"].tolist()) == list(range(31))


def test_unknown_split_and_arguments():
    with pytest.raises(ValueError, match="unknown split"):
        make_tasks("sidewalk", "validation")
    with pytest.raises(TypeError):
        make_tasks("sidewalk", "train", dataset="x")


@needs_zara
def test_tasks_for_a_sidewalk_run_read_its_data_file():
    """`envs.tasks_for` passes the run's data file; the sidewalk has no val split, so its
    validation set is its first `VAL_TASKS` (24) of the 25 training windows."""
    import jax

    from mpcpearl_jax.config import ExperimentConfig
    from mpcpearl_jax.envs import tasks_for, validation_tasks

    cfg = ExperimentConfig(env="sidewalk", data=str(ZARA), task_seed=3)
    for split in ("train", "test"):
        new, old = tasks_for(cfg, split), make_tasks("sidewalk", split, 3, data=str(ZARA))
        jax.tree_util.tree_map(np.testing.assert_array_equal, new, old)
    val, what = validation_tasks(cfg)
    first = jax.tree_util.tree_map(lambda x: x[:24], tasks_for(cfg, "train"))
    jax.tree_util.tree_map(np.testing.assert_array_equal, val, first)
    assert "first 24 training tasks" in what
    with pytest.raises(ValueError, match="no 'val' split"):
        tasks_for(cfg, "val")


@needs_zara
@pytest.mark.parametrize("how", ["centimetres", "shifted 1000 m"])
def test_a_scene_outside_the_arena_is_refused(tmp_path, how):
    """Zara 01 in centimetres, or shifted 1000 m, used to train with every person outside the
    arena; it is refused with one line naming the file and the arena."""
    rows = [line.split() for line in ZARA.read_text().splitlines() if line.strip()]
    scale, shift = (100.0, 0.0) if how == "centimetres" else (1.0, 1000.0)
    text = "".join(
        f"{f}\t{p}\t{float(x) * scale + shift:.6f}\t{float(y) * scale:.6f}\n" for f, p, x, y in rows
    )
    path = _write(tmp_path, text, "moved.txt")
    with pytest.raises(DataFormatError, match=r"moved\.txt: only \d+% of its positions") as e:
        make_tasks("sidewalk", "train", data=path)
    assert "\n" not in str(e.value) and "metres in the arena's frame" in str(e.value)
    make_tasks("sidewalk", "train", data=ZARA)  # the file itself (a few rows 0.4 m out) loads
