"""The .npz take interchange: a good take round-trips; damaged files get one clear TakeError."""

import numpy as np
import pytest

from flockcal.takes import TakeError, load_take, make_take, save_take


def _take(n=5, m=3):
    R = np.broadcast_to(np.eye(3), (n, m, 3, 3)).copy()
    t = np.arange(n * m * 3, dtype=float).reshape(n, m, 3) / 100
    return make_take(R, t, ["a", "b", "c"][:m], 100.0)


def test_a_take_round_trips_through_npz(tmp_path):
    take = _take()
    save_take(tmp_path / "t.npz", take)
    back = load_take(tmp_path / "t.npz")
    assert back.names == take.names and back.rate_hz == 100.0
    assert np.array_equal(back.positions, take.positions) and back.valid.all()


@pytest.mark.parametrize("damage", ["text", "truncated", "empty"])
def test_a_damaged_file_gets_one_clear_error(tmp_path, damage):
    good = tmp_path / "good.npz"
    save_take(good, _take())
    bad = tmp_path / "bad.npz"
    # Tried: a text file named .npz, the first 100 bytes of a real take, and an empty file.
    bad.write_bytes({"text": b"garbage\n", "truncated": good.read_bytes()[:100], "empty": b""}[damage])
    with pytest.raises(TakeError, match="not a .npz take .*truncated, or not a take"):
        load_take(bad)


def test_valid_frames_with_nan_are_refused_but_invalid_ones_may_hold_anything():
    take = _take()
    t = take.positions.copy()
    t[2, 1] = np.nan
    with pytest.raises(TakeError, match="frame 2, sensor 'b'"):
        make_take(take.rotations, t, take.names, 100.0)
    valid = np.ones((5, 3), bool)
    valid[2, 1] = False
    ok = make_take(take.rotations, t, take.names, 100.0, valid=valid)
    assert np.isfinite(ok.positions).all()  # zeros, so no NaN leaks into sums downstream
