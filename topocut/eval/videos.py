"""Rollout videos of the evaluation (``eval.videos``, ``eval.video_frames_per_cut``; docs/evaluation.md).

For every policy run (a learned policy's training seed is a run of its own, as in ``episodes/``), the first
``eval.videos`` episode specs are run again through the episode engine with the frames during each cut kept
(``run_episodes(..., frames=True, cut_frames=F)``: CuttingEnv.cut's ``record_every`` snapshots, topocut.sim.cut_frames),
drawn by the one renderer (topocut.sim.render: particles by cluster id, the knife, the board; one view box over
the whole episode) and encoded as H.264 MP4 (imageio with the imageio-ffmpeg binary) at
``videos/<run>/<task>_<object>_<episode>.mp4``.  The evaluation films as it goes (``Filming``, handed to
topocut.eval.protocol.run_evaluation, in the workers too): a batch holding a filmed episode keeps its frames, and
the video is written before the episode's JSON, so the film is the evaluated episode itself.  ``film_episodes``
films afterwards only what an interrupted evaluation left without its video, by running those episodes again (a
batch's episodes do not depend on their batch-mates and each is reset with its own seed).

Frames of a video: each state (reset, after every cut, after every turn) held ``STATE_HOLD_FRAMES`` frames (1 s),
and before each cut's state the F frames during it (the pieces coloured as before the cut, the particles this cut
has damaged so far dark, the blade at its edge of the time): ``STATE_HOLD_FRAMES * states + F * cuts`` frames.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

VIDEO_FPS = 10
STATE_HOLD_FRAMES = 10  # each state between the cuts shows for 1 s at VIDEO_FPS
VIDEO_WIDTH, VIDEO_HEIGHT = 640, 480  # multiples of 16, H.264's macroblock: the encoder need not rescale
MACRO_BLOCK = 16


def video_path(out_dir, run: str, spec) -> Path:
    """Where the video of run ``run`` on EpisodeSpec ``spec`` is written (beside episodes/<run>/<key>.json)."""
    return Path(out_dir) / run / f"{spec.key}.mp4"


def episode_video_frames(log, title: str) -> tuple[list[dict], list[int]]:
    """(render_frame arguments per distinct frame, how many video frames each lasts) of an EpisodeLog recorded
    with frames=True: the frames during each cut (``log.motion``) before the state the cut led to."""
    frames, repeats, cut = [], [], 0
    labels_before = None
    for (x, labels, what, knife), during in zip(log.frames, log.motion):
        if knife is not None:
            cut += 1
            for f in during:  # the same particles as the state before the cut: its labels colour them
                frames.append(dict(x=f.x, labels=labels_before, damaged=f.damaged, knife=knife, knife_edge=f.knife_edge,
                                   title=f"{title} cut {cut}: {1e3 * f.time_s:.0f} ms"))
                repeats.append(1)
        frames.append(dict(x=x, labels=labels, knife=knife, title=f"{title} {what}"))
        repeats.append(STATE_HOLD_FRAMES)
        labels_before = labels
    return frames, repeats


def encoder_problem() -> str | None:
    """What filming lacks on this machine (the renderer's matplotlib, imageio, the imageio-ffmpeg binary), or None.
    Asked before an evaluation starts (topocut.config.validate): a machine without an encoder finds out up front,
    not after its last episode, nor in a worker mid-evaluation."""
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg
        import matplotlib  # noqa: F401

        imageio_ffmpeg.get_ffmpeg_exe()  # raises when its binary is missing
    except Exception as e:  # noqa: BLE001 - an ImportError, or imageio-ffmpeg's RuntimeError for a missing binary
        return f"{type(e).__name__}: {e}"
    return None


def write_mp4(frames, path, fps: float = VIDEO_FPS) -> Path:
    """(H,W,3) uint8 frames to an H.264 MP4 (yuv420p: plays everywhere), padded white to one size in multiples of
    16 pixels.  Written to a temporary name in the same directory and renamed: the file is complete or absent
    (a killed run's leftover, ``.*.tmp-*``, is dropped by the artifact's commit)."""
    import imageio.v2 as imageio

    from topocut.data.store import write_atomic

    imgs = [np.asarray(f)[..., :3] for f in frames]
    if not imgs:
        raise ValueError("write_mp4 needs at least one frame")
    h = -(-max(i.shape[0] for i in imgs) // MACRO_BLOCK) * MACRO_BLOCK
    w = -(-max(i.shape[1] for i in imgs) // MACRO_BLOCK) * MACRO_BLOCK

    def encode(tmp):  # ffmpeg picks the container by the temporary name's suffix
        writer = imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                    pixelformat="yuv420p", macro_block_size=MACRO_BLOCK, ffmpeg_log_level="error")
        try:
            canvas = np.full((h, w, 3), 255, np.uint8)  # H,W,3
            for im in imgs:
                canvas[:] = 255
                canvas[:im.shape[0], :im.shape[1]] = im
                writer.append_data(canvas)
        finally:
            writer.close()

    return write_atomic(path, encode)


class Filming:
    """What run_evaluation films while it evaluates: ``keys``, the episode specs filmed for every run (the first
    ``eval.videos`` of the protocol's list), with ``frames_per_cut`` frames during each cut, under ``out_dir``."""

    def __init__(self, out_dir, keys, frames_per_cut: int):
        self.out_dir, self.keys, self.frames_per_cut = Path(out_dir), frozenset(keys), int(frames_per_cut)

    @classmethod
    def of(cls, specs, eval, out_dir) -> Filming | None:
        """The eval config's films of ``specs`` (the protocol's whole list, as pipelines/eval.py has it), or None."""
        keys = [s.key for s in list(specs)[: max(0, int(eval.videos))]]
        return cls(out_dir, keys, eval.video_frames_per_cut) if keys else None

    def wants(self, run: str, spec) -> bool:
        return spec.key in self.keys and not video_path(self.out_dir, run, spec).exists()

    def write(self, run: str, spec, log, board_z: float) -> Path | None:
        """The MP4 of ``log`` (an EpisodeLog kept with frames); None for an episode that reached no state."""
        frames, repeats = episode_video_frames(log, f"{run} {spec.key}")
        if not frames:
            return None
        from topocut.sim.render import render_frames

        # one view box over every frame of the episode: pieces pushed or turned away stay in view
        images = render_frames(frames, board_z=board_z, width=VIDEO_WIDTH, height=VIDEO_HEIGHT)
        return write_mp4([img for img, r in zip(images, repeats) for _ in range(r)], video_path(self.out_dir, run, spec))


class Films:
    """Several films as one, as run_evaluation takes them: the videos (Filming) and the cutting sequences
    (topocut.eval.sequences.Sequences).  A batch keeps the most frames during a cut any member asks for, and each
    member writes what it wants of an episode."""

    def __init__(self, *members):
        self.members = [m for m in members if m is not None]
        self.keys = frozenset().union(*(m.keys for m in self.members))
        self.frames_per_cut = max((m.frames_per_cut for m in self.members), default=0)

    @classmethod
    def of(cls, *members) -> Films | None:
        films = cls(*members)
        return films if films.members else None

    def wants(self, run: str, spec) -> bool:
        return any(m.wants(run, spec) for m in self.members)

    def write(self, run: str, spec, log, board_z: float) -> list:
        return [m.write(run, spec, log, board_z) for m in self.members if m.wants(run, spec)]


def film_episodes(specs, policies: dict, env, task_cfgs: dict, out_dir, eval, reward, topology, observe_fn,
                  spacing, film: Filming | Films | None = None, **score_fns) -> int:
    """For every run of ``policies`` ({run: policy}), the episodes of ``specs`` that ``film`` wants and has not
    written: their films (an MP4 each under ``out_dir``, video_path; a cutting sequence's GIF), each episode run
    again with frames.  The evaluation films as it goes (Films), so this is left only what an interrupted
    evaluation committed without its films.  ``film``: what to film (default: Filming.of the config);
    ``score_fns``: goal_fn, discover_fn, reward_fn as run_evaluation takes them.  Returns how many episodes this
    call ran again."""
    from topocut.episode import env_board_z, make_scoring, run_episodes
    from topocut.eval.protocol import _episode

    film = film if film is not None else Filming.of(specs, eval, out_dir)
    if film is None:
        return 0
    chosen = [s for s in specs if s.key in film.keys]
    sc = make_scoring(reward, topology, min_fragment_points=eval.min_fragment_points, env=env, **score_fns)
    board_z, written = env_board_z(env), 0
    for run, policy in policies.items():
        todo = [s for s in chosen if film.wants(run, s)]
        if not todo:
            continue
        logs = run_episodes(env, [_episode(s, task_cfgs[s.task]) for s in todo], policy, sc, max_cuts=eval.max_cuts,
                            observe_fn=observe_fn, stop_on_success=eval.stop_on_success, spacing=spacing, frames=True,
                            cut_frames=film.frames_per_cut)
        for spec, log in zip(todo, logs):
            film.write(run, spec, log, board_z)
            written += 1
    return written
