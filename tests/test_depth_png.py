"""The one depth-PNG codec (`data.depth_png`): round(metres x 256), 0 = no depth, and depth over
255.996 m written as 255.996 m with a counted warning, never silently (issue 42: the dataset writer
raised at 256 m while predict clipped without a word)."""

import warnings

import numpy as np
import pytest

from irdepth_jax.data.depth_png import MAX_COUNT, DepthRangeWarning, OverRange, decode_depth, encode_depth
from irdepth_jax.data.folder import write_sample


def test_encoding_of_depths_in_range():
    """Valid depths under 1/512 m stay a depth (one count); 0 and negative depths are 'no depth'."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        counts = encode_depth(np.array([0.0, 1 / 256, 1e-4, 255.99, -1.0, 10.0]),
                              np.array([True, True, True, True, True, False]))
    np.testing.assert_array_equal(counts, [0, 1, 1, 65533, 0, 0])
    depth, valid = decode_depth(counts)
    np.testing.assert_array_equal(valid, [False, True, True, True, False, False])
    np.testing.assert_allclose(depth[valid], [1 / 256, 1 / 256, 65533 / 256])


def test_depth_over_the_range_is_written_as_the_largest_and_counted():
    with pytest.warns(DepthRangeWarning) as caught:
        counts = encode_depth(np.array([[255.99, 256.0], [300.0, 0.0]]), name="frame a")
    np.testing.assert_array_equal(counts, [[65533, MAX_COUNT], [MAX_COUNT, 0]])
    [warning] = caught
    assert str(warning.message) == ("2 depth values of frame a are over 255.996 m (up to 300.00 m), "
                                    "the most a 16-bit depth PNG holds: written as 255.996 m")


def test_a_tally_over_many_maps_gives_one_line():
    tally = OverRange()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # counted in the tally, no warning per map
        for name, depth in [("a", [1.0, 2.0]), ("b", [400.0, 1.0]), ("c", [257.0, 999.5])]:
            encode_depth(np.array(depth), name=name, over_range=tally)
    assert tally.message() == ("3 depth values of 2 depth maps (the first: b) are over 255.996 m "
                               "(up to 999.50 m), the most a 16-bit depth PNG holds: written as "
                               "255.996 m")
    assert OverRange().message() is None


def test_dataset_writer_warns_instead_of_failing(tmp_path):
    """A depth label of 300 m: the sample is written (at 255.996 m) with a warning naming it."""
    raw = np.full((4, 6), 5000, np.uint16)
    depth = np.full((4, 6), 20.0)
    depth[0, 0] = 300.0
    with pytest.warns(DepthRangeWarning, match="1 depth values of sample s0 are over 255.996 m"):
        fields = write_sample(tmp_path, "s0", {"raw14": raw, "ir8": np.zeros((4, 6), np.uint8),
                                               "depth": depth})
    assert fields["max_depth"] == MAX_COUNT / 256
