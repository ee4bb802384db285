"""metrics.png: one panel per kind of figure, each series keyed by colour in its legend."""

import json

import numpy as np
from PIL import Image

from policy.plot import COLORS, plot_metrics


def _write(path, rows):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_panels_follow_what_the_run_logged(tmp_path):
    m = tmp_path / "metrics.jsonl"
    assert plot_metrics(m, tmp_path / "none.png") is None  # nothing logged yet: no picture
    rows = [{"step": s, "loss": 1.0 / s, "lr": 1e-4} for s in range(10, 110, 10)]
    _write(m, rows)
    assert Image.open(plot_metrics(m, tmp_path / "a.png")).size == (800, 2 * 225 + 50)  # loss, lr
    rows += [{"step": 50, "val_loss": 0.2, "fit_loss": 0.1, "val_grasp_cm": 9.0, "fit_grasp_cm": 4.0},
             {"step": 100, "val_loss": 0.1, "fit_loss": 0.05, "val_grasp_cm": 8.0, "fit_grasp_cm": 3.0,
              "guess_grasp_cm": 12.0}]
    _write(m, rows)
    img = np.asarray(Image.open(plot_metrics(m, tmp_path / "b.png")).convert("RGB"))
    assert img.shape[:2] == (3 * 225 + 50, 800)  # + grasp-point error
    legend = img[20 + 2 * 225 + 3:20 + 2 * 225 + 12, 50:]  # the grasp panel's legend row, above its lines

    def has(color):
        from PIL import ImageColor

        rgb = np.array(ImageColor.getrgb(color))
        return bool((np.abs(legend.astype(int) - rgb).sum(-1) < 60).any())

    assert all(has(c) for c in COLORS)  # each of the three series names itself in its line's colour
