"""A contact sheet of randomized episodes: see at a glance what a DR preset (or TOML) does to the scene.

Each tile is one seed: the first frame of every requested camera, side by side, with the sensor noise of
that episode applied, and a caption (seed, light count, image noise). Seeds run seed..seed+count-1, so a
grid is reproducible and a tile can be rebuilt alone with `build_world(task, seed=..., dr=...)`.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from sim.dr_config import DRConfig, load_dr
from sim.randomize import corrupt_image, episode_sensor_params
from sim.render import CameraRenderer
from sim.robot import WRIST_CAMERA
from sim.scene import SCENE_CAMERA

_CAPTION_H = 22
_GAP = 6
_BG = (24, 24, 28)
_FG = (235, 235, 235)


def render_episode(task: str | None, cfg: DRConfig, seed: int, cameras, size,
                   fidelity: str = "full") -> tuple[list[np.ndarray], str]:
    """First frames of `cameras` for episode `seed`, corrupted by its sensor params, and a caption."""
    from sim.build import build_episode

    episode = build_episode(task, seed, cfg, fidelity=fidelity)
    params = episode_sensor_params(episode)
    frames = []
    with CameraRenderer(episode.world, *size) as renderer:
        for cam in cameras:
            frames.append(corrupt_image(renderer.rgb(cam), params, episode.rngs.sensor))
    lights = episode.dr_record.get("light_count", 0)
    caption = f"seed {seed} | {lights} light{'s' if lights != 1 else ''} | noise {params.image_noise_std:.1f}"
    return frames, caption


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has only the fixed bitmap font
        return ImageFont.load_default()


def preview_grid(task: str | None, dr: str | DRConfig, seed: int, out: Path, count: int = 12,
                 cameras=(SCENE_CAMERA, WRIST_CAMERA), size=(320, 240), fidelity: str = "full") -> Path:
    """Render `count` episodes (seeds seed..seed+count-1) and write them as one tiled PNG at `out`.

    Episodes come from `sim.build.build_episode`, so a tile shows exactly what training would see for that
    seed (objects settled, DR applied); `fidelity="fast"` trades robot meshes and shadows for speed.
    """
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    cfg = dr if isinstance(dr, DRConfig) else load_dr(dr)
    width, height = int(size[0]), int(size[1])
    tile_w = len(cameras) * width + (len(cameras) - 1) * 2
    tile_h = _CAPTION_H + height
    # Aim for a roughly 16:10 sheet: cols * tile_w ~ 1.6 * rows * tile_h.
    cols = max(1, min(count, math.ceil(math.sqrt(1.6 * count * tile_h / tile_w))))
    rows = math.ceil(count / cols)
    header = 28
    sheet = Image.new("RGB", (cols * tile_w + (cols + 1) * _GAP, header + rows * tile_h + (rows + 1) * _GAP), _BG)
    draw = ImageDraw.Draw(sheet)
    title = (f"task {task or '(bare scene)'} | DR {cfg.preset} | seeds {seed}..{seed + count - 1} | "
             f"fidelity {fidelity} | cameras: {', '.join(cameras)}")
    draw.text((_GAP, 6), title, fill=_FG, font=_font(16))
    font = _font(14)
    for k in range(count):
        frames, caption = render_episode(task, cfg, seed + k, cameras, (width, height), fidelity)
        r, c = divmod(k, cols)
        x0 = _GAP + c * (tile_w + _GAP)
        y0 = header + _GAP + r * (tile_h + _GAP)
        draw.text((x0 + 2, y0 + 3), caption, fill=_FG, font=font)
        for i, frame in enumerate(frames):
            sheet.paste(Image.fromarray(frame), (x0 + i * (width + 2), y0 + _CAPTION_H))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 320x240") from None
    if not (16 <= w <= 1280 and 16 <= h <= 960):
        raise argparse.ArgumentTypeError(f"--size {text!r}: each side must be in 16..1280 x 16..960")
    return w, h


def _task_names() -> list[str]:
    from sim.tasks import task_names

    return task_names()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m sim.preview",
        description="Render the first frame of several randomized episodes into one PNG contact sheet, to\n"
                    "check what a domain-randomization preset or TOML file does before generating data.\n"
                    "Each tile is one seed: the scene and wrist cameras side by side, with that episode's\n"
                    "sensor noise, captioned with the seed, the light count and the image noise std.",
        epilog="examples:\n"
               "  python -m sim.preview --task pick_place --dr heavy --seed 0 --out grid.png\n"
               "  python -m sim.preview --dr light --count 6 --cameras scene_cam --out light.png\n"
               "  python -m sim.preview --dr my_dr.toml --out mine.png   "
               "# TOML: preset = \"light\" plus e.g. [visual] light_count = [1, 4]\n"
               "A tile is reproducible: build_world(task, seed=S, dr=...) rebuilds exactly that scene.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default=None,
                        help=f"task family whose objects to place, one of {', '.join(_task_names())} "
                             "(default: the bare scene without objects)")
    parser.add_argument("--dr", default="heavy",
                        help="DR preset off|light|heavy, or a .toml file overriding a preset (default: heavy)")
    parser.add_argument("--seed", type=int, default=0, help="first episode seed (default: 0)")
    parser.add_argument("--count", type=int, default=12, help="number of episodes / tiles (default: 12)")
    parser.add_argument("--out", type=Path, default=Path("dr_preview.png"), help="PNG to write")
    parser.add_argument("--cameras", nargs="+", default=[SCENE_CAMERA, WRIST_CAMERA],
                        help=f"cameras per tile (default: {SCENE_CAMERA} {WRIST_CAMERA})")
    parser.add_argument("--fidelity", default="full", choices=("full", "fast"),
                        help="full: mesh robot and shadows; fast: primitive robot, no shadows (default: full)")
    parser.add_argument("--size", type=_size, default=(320, 240),
                        help="per-camera image WIDTHxHEIGHT (default: 320x240)")
    args = parser.parse_args(argv)
    from sim.config import ConfigError

    try:
        path = preview_grid(args.task, args.dr, args.seed, args.out, args.count, tuple(args.cameras), args.size,
                            args.fidelity)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
