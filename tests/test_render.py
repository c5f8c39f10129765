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
