"""Saving episodes as GIF (Pillow, always available) or MP4 (only with the optional imageio-ffmpeg).

Works with any env built with ``render_mode="rgb_array"``: the grid, and cheetah / walker headless
through ``MUJOCO_GL`` (egl, or osmesa; see :mod:`drago.envs.dmc`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Recording", "record_episode", "save_gif", "save_video"]


def save_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float) -> Path:
    """Write RGB frames (H, W, 3, uint8) as a looping GIF; GIF timing has 10 ms resolution."""
    from PIL import Image

    if not frames:
        raise ValueError("no frames to save")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    duration = max(10, int(round(100.0 / fps)) * 10)
    images[0].save(path, save_all=True, append_images=images[1:], duration=duration, loop=0)
    return path


def _save_mp4(frames: Sequence[np.ndarray], path: Path, fps: float) -> Path:
    try:
        import imageio_ffmpeg
    except ImportError:
        raise RuntimeError("MP4 needs the optional package imageio-ffmpeg (pip install imageio-ffmpeg); "
                           "or save a .gif, which needs nothing extra") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    height, width = np.asarray(frames[0]).shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (width, height), fps=fps, macro_block_size=1)
    writer.send(None)  # start the generator
    try:
        for frame in frames:
            writer.send(np.ascontiguousarray(frame, dtype=np.uint8))
    finally:
        writer.close()
    return path


def save_video(frames: Sequence[np.ndarray], path: str | Path, fps: float) -> Path:
    """Save frames as ``.gif`` or ``.mp4``, chosen by the file's suffix."""
    path = Path(path)
    if not frames:
        raise ValueError("no frames to save")
    suffix = path.suffix.lower()
    if suffix == ".gif":
        return save_gif(frames, path, fps)
    if suffix == ".mp4":
        return _save_mp4(frames, path, fps)
    raise ValueError(f"unsupported video format '{path.suffix}'; use .gif or .mp4")


@dataclass
class Recording:
    path: Path
    episode_return: float
    frames: int


def record_episode(env, length: int, choose_action: Callable[[np.ndarray, int], np.ndarray], path: str | Path,
                   fps: float | None = None, seed: int | None = None) -> Recording:
    """Roll one episode of ``length`` agent steps and save one frame per step (plus the first).

    Args:
        env: a gymnasium env created with ``render_mode="rgb_array"``.
        length: agent steps to take.
        choose_action: ``(obs, t) -> action``, as for :func:`drago.training.trainer.run_episode`
            (for example ``lambda obs, t: agent.act(obs, step, eval_mode=True, first_step=t == 0)``).
        path: ``.gif`` or ``.mp4`` file to write.
        fps: frames per second (None: the env's ``metadata["render_fps"]``, real time for DMC).
        seed: passed to ``env.reset``.

    Returns:
        The file written, the episode's undiscounted return and the number of frames.
    """
    fps = fps or env.metadata.get("render_fps") or 25
    obs, _ = env.reset(seed=seed)
    frames = [env.render()]
    total = 0.0
    for t in range(length):
        obs, reward, _, _, _ = env.step(choose_action(obs, t))
        total += float(reward)
        frames.append(env.render())
    return Recording(save_video(frames, path, fps), total, len(frames))
