"""The figures' geometry: the drawn blade lies in the cut's plane with its edge on the board, and the
cutting-sequence figure draws one panel per state (pixels checked, not just that a file exists)."""
import numpy as np
import pytest

from topocut.sim.action import KnifeAction, signed_distance_to_plane
from topocut.sim.render import blade_corners, render_sequences, row_limits


@pytest.mark.parametrize("yaw,tilt", [(0.0, 0.0), (0.7, 0.0), (-1.2, 0.5), (0.3, -0.6)])
def test_the_blade_is_drawn_in_the_cut_plane_with_its_edge_on_the_board(yaw, tilt):
    a = KnifeAction(0.47, 0.52, yaw, tilt)
    board_z, center = 0.05, np.array([0.5, 0.5, 0.1])
    c = blade_corners(a, board_z, center=center, half_length=0.08, height=0.1)  # 4,3
    assert np.abs(signed_distance_to_plane(c, a, board_z)).max() < 1e-12
    np.testing.assert_allclose(c[:2, 2], board_z, atol=1e-12)  # the edge lies on the board
    assert (c[2:, 2] > board_z + 0.1 * np.cos(tilt) - 1e-9).all()  # the back is above, along the blade plane
    np.testing.assert_allclose(np.linalg.norm(c[1] - c[0]), 0.16)
    np.testing.assert_allclose(np.linalg.norm(c[3] - c[0]), 0.1)
    mid = c[:2].mean(0)  # centred at the centre's projection on the edge line: the offset is normal to u
    assert abs(np.dot(mid - center, a.blade_axis)) < 1e-12


def test_the_sequence_figure_has_a_panel_per_state_and_draws_the_knife(tmp_path):
    import imageio.v2 as imageio

    rng = np.random.default_rng(0)
    x = rng.uniform([0.45, 0.45, 0.05], [0.55, 0.55, 0.12], (400, 3))
    lab = (x[:, 0] > 0.5).astype(int)
    cut = KnifeAction(0.5, 0.5)
    rows = [("slice: cube", [(x, np.zeros(400, int), None, "initial"), (x, lab, None, "goal"),
                             (x, lab, cut, "cut 1")]),
            ("dice: cube", [(x, np.zeros(400, int), None, "initial")])]
    plain = render_sequences(rows, tmp_path / "a.png", board_z=0.05, dpi=60)
    img = imageio.imread(plain)
    h, w = img.shape[:2]
    assert w > 2.5 * h / 2 * 0.9  # 3 columns by 2 rows of square-ish panels
    def panel(im, r, c):  # the middle 60% of grid cell (r, c): clear of the margins and the neighbours
        y0, x0, ph, pw = r * h // 2, c * w // 3, h // 2, w // 3
        return im[y0 + ph // 5:y0 + 4 * ph // 5, x0 + pw // 5:x0 + 4 * pw // 5, :3].astype(int)

    blank = panel(img, 1, 1)  # row 2 has one panel: its second column is empty
    assert (blank == 255).all()
    assert (panel(img, 1, 0) != 255).any()
    # the knife's panel differs from the same scene without the knife by the blade's blue
    rows[0][1][2] = (x, lab, None, "cut 1")
    img2 = imageio.imread(render_sequences(rows, tmp_path / "b.png", board_z=0.05, dpi=60))
    with_knife, without = panel(img, 0, 2), panel(img2, 0, 2)
    bluish = lambda p: ((p[..., 2] > p[..., 0] + 30) & (p[..., 2] > 120)).sum()  # noqa: E731
    assert bluish(with_knife) > bluish(without) + 20
    assert (panel(img, 0, 1) == panel(img2, 0, 1)).all()  # the other panels are the same


def test_a_row_spans_every_panel_so_pieces_pushed_away_stay_in_view():
    initial = np.array([[0.45, 0.45, 0.06], [0.55, 0.55, 0.12]])
    pushed = np.array([[0.50, 0.50, 0.06], [0.68, 0.52, 0.09]])  # a piece slid 0.13 past the object's edge
    lo, hi = row_limits([initial, pushed], board_z=0.05, pad=0.02)
    np.testing.assert_allclose(lo, [0.43, 0.43, 0.04])  # the board (0.05) is above lo - pad: lo z = 0.06 - 0.02
    np.testing.assert_allclose(hi, [0.70, 0.57, 0.14])
    lo, _ = row_limits([initial + [0, 0, 0.2]], board_z=0.05)
    assert lo[2] == 0.05  # a scene floating above the board still shows the board


# -- the renderer on a simulated sequence: a cut recorded in motion, a push, a turn ---------------------------------
@pytest.fixture(scope="module")
def sequence():
    """A cube cut with snapshots every 32 substeps, pushed, and its slab turned and laid down far right (n_grid 32)."""
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import Turn

    env = CuttingEnv(SimConfig(n_grid=32, settle_time=0.0), batch_size=1)
    env.reset("cube", ObjectPose(x=0.45, y=0.5, yaw=0.0, scale=1.0))
    x0 = env.state().x[0]
    cut = KnifeAction(x=0.49, y=0.5)
    info = env.cut(cut, record_every=32)
    x_cut = env.state().x[0]
    env.push()
    x_push = env.state().x[0]
    piece = env.piece[0].copy()  # N, the simulator's piece ids: 0, 1
    slab = piece == np.bincount(piece[x_push[:, 0] > 0.5]).argmax()  # the piece right of the cut
    env.turn(Turn("slab", (0.0, 1.0, 0.0), np.pi / 2, tuple(x_push[slab].mean(0) + [0.01, 0, 0]), (0.75, 0.5, 0.2)))
    states = [dict(x=x0, labels=np.zeros(len(x0), int)), dict(x=x_cut, labels=piece, knife=cut),
              dict(x=x_push, labels=piece, knife=cut), dict(x=env.state().x[0], labels=piece)]
    return env, info, states


def test_a_recorded_cut_moves_its_particles_and_knife_and_recording_changes_nothing(sequence):
    from topocut.sim.action import signed_distance_to_plane
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.objects import ObjectPose

    env, info, states = sequence
    snaps, board_z = info.snapshots, env.cfg.board_z
    assert len(snaps) >= 5 and [s.substep for s in snaps] == sorted({s.substep for s in snaps})
    assert snaps[-1].substep <= info.substeps
    for a, b in zip(snaps, snaps[1:]):  # the particles move and the blade damages more between consecutive snapshots
        assert np.abs(b.x[0] - a.x[0]).max() > 1e-5  # (a cut displaces little: the pieces part by their own fields)
        assert b.damage[0].sum() > a.damage[0].sum()
    edges = np.stack([s.knife_edge[0] for s in snaps])  # S,3
    assert (np.diff(edges[:, 2]) <= 1e-9).all() and edges[0, 2] > edges[-1, 2] + 0.05  # the blade goes down
    assert abs(edges[-1, 2] - board_z) < env.cfg.dx  # ... to the board
    assert np.abs(signed_distance_to_plane(edges, KnifeAction(x=0.49, y=0.5), board_z)).max() < 1e-6  # in its plane
    assert snaps[-1].damage[0].sum() > 0
    # the same cut without recording: bit for bit the same state (one CPU thread: atomics in a fixed order)
    plain = CuttingEnv(SimConfig(n_grid=32, settle_time=0.0), batch_size=1)
    plain.reset("cube", ObjectPose(x=0.45, y=0.5, yaw=0.0, scale=1.0))
    assert plain.cut(KnifeAction(x=0.49, y=0.5)).snapshots is None
    np.testing.assert_array_equal(plain.state().x[0], states[1]["x"])


def _pixels(frame, fig, ax, x):
    """Particles (N,3) to the frame's pixel coordinates (N,2), column and row from the top-left (matplotlib's own
    projection of the axes the frame was drawn with)."""
    from mpl_toolkits.mplot3d import proj3d

    px = ax.transData.transform(np.stack(proj3d.proj_transform(*np.asarray(x).T, ax.get_proj())[:2], 1))  # N,2
    return np.stack([px[:, 0], frame.shape[0] - px[:, 1]], 1), ax.bbox


def test_every_particle_stays_in_frame_after_a_cut_a_push_and_a_turn(sequence):
    from topocut.sim.render import frame_figure, render_frame, render_frames, sequence_limits

    env, _, states = sequence
    board_z = env.cfg.board_z
    lo0, hi0 = states[0]["x"].min(0), states[0]["x"].max(0)
    turned = states[-1]["x"]
    assert (turned > hi0 + 0.05).any() or (turned < lo0 - 0.05).any()  # a first-frame view would crop the turn
    frames = render_frames(states, board_z=board_z)
    limits = sequence_limits([s["x"] for s in states], board_z)
    for state, frame in zip(states, frames):
        h, w = frame.shape[:2]
        assert frame.dtype == np.uint8 and frame.shape == (600, 800, 3)  # >= 800 px wide
        np.testing.assert_array_equal(frame, render_frame(board_z=board_z, limits=limits, **state))  # one view box
        fig, ax = frame_figure(board_z=board_z, limits=limits, **state)
        fig.canvas.draw()
        assert fig.canvas.get_width_height() == (w, h)
        px, box = _pixels(frame, fig, ax, state["x"])
        assert ((px >= 0) & (px < [w, h])).all()
        # inside the 3D axes, clear of the title and the legend
        assert (px[:, 0] >= box.x0).all() and (px[:, 0] <= box.x1).all()
        assert (h - px[:, 1] >= box.y0).all() and (h - px[:, 1] <= box.y1).all()
        assert px[:, 0].max() - px[:, 0].min() > 0.2 * w  # and not lost in a corner: the scene fills the frame
    # the check sees cropping: the turned slab in the first frame's view box (the old renderer's) leaves the frame
    fig, ax = frame_figure(board_z=board_z, limits=sequence_limits([states[0]["x"]], board_z), **states[-1])
    fig.canvas.draw()
    px, _ = _pixels(frames[-1], fig, ax, turned)
    assert (~((px >= 0) & (px < [w, h])).all(1)).sum() > 20


def test_knife_board_and_legend_are_drawn(sequence):
    from topocut.sim.render import _PALETTE, BOARD_FACE, UNASSIGNED, cluster_colors, frame_figure, render_frame

    env, _, states = sequence
    s, bz = states[2], env.cfg.board_z  # after the push: the knife at the cut's plane
    magenta = (1.0, 0.0, 1.0, 1.0)
    with_knife = render_frame(s["x"], s["labels"], knife=s["knife"], knife_color=magenta, board_z=bz).astype(int)
    bare = render_frame(s["x"], s["labels"], board_z=None).astype(int)
    limits = (s["x"].min(0) - 0.02, s["x"].max(0) + 0.02)
    no_board = render_frame(s["x"], s["labels"], limits=limits).astype(int)
    board = render_frame(s["x"], s["labels"], board_z=bz, limits=limits).astype(int)
    is_magenta = lambda f: ((f[..., 0] > 200) & (f[..., 1] < 60) & (f[..., 2] > 200)).sum()  # noqa: E731
    assert is_magenta(with_knife) > 2000 and is_magenta(bare) == 0
    wood = np.round(255 * (1 - BOARD_FACE[3] * (1 - np.asarray(BOARD_FACE[:3])))).astype(int)  # over white
    is_wood = lambda f: (np.abs(f - wood).max(-1) <= 3).sum()  # noqa: E731
    assert is_wood(board) > 5000 and is_wood(no_board) == 0
    # cluster 0 is not the colour of unassigned particles; the legend names the pieces, the knife and the board
    assert np.abs(_PALETTE - UNASSIGNED).sum(1).min() > 0.3
    assert not np.allclose(cluster_colors([0]), cluster_colors([-1]))
    fig, _ = frame_figure(s["x"], np.where(s["labels"] == 1, -1, 0), knife=s["knife"], board_z=bz)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["piece 0", "unassigned", "knife", "board"]
    with pytest.raises(ValueError, match="labels"):
        render_frame(s["x"], s["labels"][:10])


def test_the_cut_gif_has_frames_from_during_the_cut(sequence, tmp_path):
    from PIL import Image

    from topocut.sim.render import render_frames, write_gif

    env, info, states = sequence
    during = [dict(x=s.x[0], labels=np.zeros(len(s.x[0]), int), damaged=s.damage[0], knife=states[1]["knife"],
                   knife_edge=s.knife_edge[0]) for s in info.snapshots]
    frames = render_frames([states[0], *during, *states[1:]], board_z=env.cfg.board_z)
    holds = [1.0] + [0.1] * len(during) + [1.0] * 3
    with Image.open(write_gif(frames, tmp_path / "cut.gif", durations=holds)) as gif:
        assert gif.n_frames == len(frames) > 1 + 3  # more than the states between cuts
        decoded = []
        for i in range(gif.n_frames):
            gif.seek(i)
            decoded.append(np.asarray(gif.convert("RGB")).astype(int))
            assert gif.info["duration"] == round(1000 * holds[i])
    for a, b in zip(decoded[1:len(during)], decoded[2:len(during) + 1]):  # consecutive frames within the cut differ
        assert (np.abs(a - b).max(-1) > 40).sum() > 200
