"""Logger.log_image: a picture reaches TensorBoard whole; loggers without TensorBoard ignore it."""

from __future__ import annotations

import numpy as np
from tensorboard.backend.event_processing.event_accumulator import IMAGES, EventAccumulator

from coworld.training.logger import Logger


def read_images(logdir) -> dict:
    events = EventAccumulator(str(logdir / "tb"), size_guidance={IMAGES: 0})
    events.Reload()
    return {tag: events.Images(tag) for tag in events.Tags()["images"]}


def test_image_is_written_to_tensorboard_at_its_step(tmp_path):
    image = np.zeros((30, 50, 3), np.uint8)
    image[:, :25] = 255
    with Logger(tmp_path, outputs=("tensorboard",)) as logger:
        logger.log_image("openl/task", image, step=7)
        logger.log_image("openl/task", image, step=9)
    images = read_images(tmp_path)
    assert list(images) == ["openl/task"]
    assert [(e.step, e.width, e.height) for e in images["openl/task"]] == [(7, 50, 30), (9, 50, 30)]
    import io

    import imageio.v2 as imageio

    decoded = imageio.imread(io.BytesIO(images["openl/task"][0].encoded_image_string))
    np.testing.assert_array_equal(decoded[..., :3], image)


def test_without_tensorboard_nothing_is_written(tmp_path):
    with Logger(tmp_path, outputs=("jsonl",)) as logger:
        logger.log_image("openl/task", np.zeros((4, 4, 3), np.uint8), step=1)
    assert not (tmp_path / "tb").exists() and (tmp_path / "metrics.jsonl").read_text() == ""


FULL_TB = """
import resource, sys
import numpy as np
from coworld.errors import StorageError
from coworld.training.logger import Logger
logger = Logger(sys.argv[1], outputs=("tensorboard",))
logger.log({"wm/loss": 1.0}, step=1)
resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, resource.RLIM_INFINITY))  # the disk fills up
try:
    for step in range(2, 50):
        logger.log_image("openl/x", np.random.default_rng(step).integers(0, 255, (256, 256, 3), np.uint8), step)
    logger.close()
except StorageError as err:
    print(f"error: {err}", file=sys.stderr)
    sys.exit(2)
"""


def test_a_full_disk_under_tensorboards_writer_thread_is_one_line_naming_the_folder(tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", FULL_TB, str(tmp_path)], capture_output=True, text=True, timeout=60)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert lines[0] == f"error: cannot write TensorBoard events in {tmp_path / 'tb'}: File too large", lines[0]
