"""Labelled grids and PNG / GIF / MP4 files."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest

from coworld.errors import CoworldError
from coworld.pictures import labelled_grid, stack_frames
from coworld.viz.media import output_kind, write_image, write_video


def solid(colour: tuple[int, int, int], h: int = 8, w: int = 6) -> np.ndarray:
    return np.broadcast_to(np.array(colour, np.uint8), (h, w, 3)).copy()


def count(image: np.ndarray, colour: tuple[int, int, int]) -> int:
    return int((image == np.array(colour, np.uint8)).all(-1).sum())


@pytest.mark.parametrize("scale", [1, 3])
def test_grid_holds_every_cell_whole_and_scaled(scale):
    colours = [[(250, 0, 0), (0, 250, 0), (0, 0, 250)], [(250, 250, 0), (0, 250, 250), (250, 0, 250)]]
    cells = [[solid(c) for c in row] for row in colours]
    grid = labelled_grid(cells, row_labels=["a", "bb"], col_labels=["0", "1", "2"], title="title", scale=scale)
    for row in colours:
        for colour in row:  # each cell once, enlarged scale times in both directions; text never uses these colours
            assert count(grid, colour) == 8 * 6 * scale**2
    assert grid.dtype == np.uint8 and grid.shape[0] > 2 * 8 * scale and grid.shape[1] > 3 * 6 * scale


def test_grid_refuses_cells_of_different_sizes():
    with pytest.raises(ValueError, match="cell"):
        labelled_grid([[solid((1, 2, 3)), solid((1, 2, 3), h=9)]])


def test_output_kind_by_suffix():
    assert output_kind("a/b.PNG") == "image"
    assert output_kind("x.mp4") == "video" and output_kind("x.gif") == "video"
    with pytest.raises(CoworldError, match=r"\.jpg.*\.png, \.mp4, \.gif"):
        output_kind("x.jpg")


def test_png_round_trip_is_exact_and_leaves_no_temporary_file(tmp_path):
    image = np.random.default_rng(0).integers(0, 256, (17, 23, 3), dtype=np.uint8)
    write_image(tmp_path / "a.png", image)
    np.testing.assert_array_equal(imageio.imread(tmp_path / "a.png")[..., :3], image)
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]


def test_a_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "a.png"
    path.write_bytes(b"old")
    with pytest.raises(Exception):  # noqa: B017 - whatever the encoder raises
        write_image(path, np.zeros((4, 4, 7), np.uint8))
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["a.png"]


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_video_has_every_frame_at_even_size(tmp_path, suffix):
    frames = np.zeros((7, 33, 41, 3), np.uint8)
    frames[:, 8:24, 8:30] = np.arange(7, dtype=np.uint8)[:, None, None, None] * 30 + 40
    path = write_video(tmp_path / f"v{suffix}", frames, fps=5)
    read = imageio.mimread(path, memtest=False)
    assert len(read) == 7
    assert read[0].shape[:2] == (34, 42)  # padded with white to even sides for H.264 (and the same for GIF)
    brightness = [float(frame[12:20, 12:26, :3].mean()) for frame in read]
    assert brightness == sorted(brightness) and brightness[-1] - brightness[0] > 120  # frames kept in order


def test_stack_frames_pads_to_the_largest():
    out = stack_frames([solid((1, 1, 1), 2, 3), solid((2, 2, 2), 4, 1)])
    assert out.shape == (2, 4, 3, 3)
    assert count(out[0], (1, 1, 1)) == 6 and count(out[1], (2, 2, 2)) == 4
