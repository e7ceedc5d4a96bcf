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
