"""Point-set metrics against hand-computed values; FPS coverage and equivariance."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from topocut.metrics import chamfer, emd, fps, fps_torch, hausdorff


def lattice(nx, ny, nz, h=0.01):
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    return g * h


def test_two_point_clouds_by_hand():
    a = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    b = np.array([[0.0, 0, 0], [0.0, 3.0, 0]])
    # a->b nearest: 0, 1 (mean 0.5); b->a nearest: 0, 3 (mean 1.5)
    assert chamfer(a, b) == pytest.approx(0.5 * (0.5 + 1.5))
    assert hausdorff(a, b) == pytest.approx(3.0)
    # bijections: {0-0, 1-(0,3)}: 0 + sqrt(10) ; {0-(0,3), 1-0}: 3 + 1 -> optimum sqrt(10)/2
    assert emd(a, b) == pytest.approx(min(np.sqrt(10.0), 4.0) / 2)


def test_shifted_copy_gives_shift_for_all_metrics():
    a = lattice(6, 5, 4, h=0.01)
    t = np.array([0.001, -0.002, 0.0015])  # |t| = 0.0027 < spacing / 2
    b = (a + t)[np.random.default_rng(0).permutation(len(a))]
    for f in (chamfer, hausdorff, emd):
        assert f(a, b) == pytest.approx(np.linalg.norm(t), rel=1e-9)


def test_one_outlier_hausdorff_and_chamfer():
    a = lattice(4, 4, 4, h=0.01)
    b = np.concatenate([a, [[0.03, 0.03, 0.13]]])  # one extra point 0.1 above the top corner
    assert hausdorff(a, b) == pytest.approx(0.1)
    assert chamfer(a, b) == pytest.approx(0.5 * 0.1 / len(b))


def test_emd_exceeds_chamfer_when_mass_must_travel():
    # a: two points at 0; b: one at 0 and one at 1: nearest-neighbour ignores the duplicate, EMD does not
    a = np.array([[0.0, 0, 0], [0.0, 0, 0]])
    b = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    assert chamfer(a, b) == pytest.approx(0.5 * (0 + 0.5))
    assert emd(a, b) == pytest.approx(0.5)


def test_emd_unequal_sizes_is_close_for_dense_same_shape():
    rng = np.random.default_rng(1)
    a, b = rng.random((300, 3)), rng.random((400, 3))
    e_same = emd(a, b)
    e_shift = emd(a, b + np.array([0.5, 0, 0]))
    assert e_shift > 0.45 and e_same < 0.2


def test_torch_matches_numpy_and_is_differentiable():
    rng = np.random.default_rng(2)
    a, b = rng.random((2, 40, 3)), rng.random((2, 40, 3))
    ta = torch.tensor(a, requires_grad=True)
    tb = torch.tensor(b)
    for f in (chamfer, hausdorff, emd):
        out = f(ta, tb)
        assert out.shape == (2,)
        np.testing.assert_allclose(out.detach().numpy(), [f(a[i], b[i]) for i in range(2)], rtol=1e-9)
    # EMD gradient: d/da mean_i |a_i - b_s(i)| = (a_i - b_s(i)) / |.| / N, checked by finite differences
    e = emd(ta, tb).sum()
    e.backward()
    eps, i, k = 1e-6, 3, 1
    a2 = a.copy()
    a2[0, i, k] += eps
    fd = (emd(a2[0], b[0]) - emd(a[0], b[0])) / eps
    assert ta.grad[0, i, k].item() == pytest.approx(fd, rel=1e-3, abs=1e-6)


def test_fps_covers_and_is_equivariant():
    rng = np.random.default_rng(3)
    pts = rng.random((2000, 3))
    idx = fps(pts, 64)
    assert len(set(idx.tolist())) == 64
    # the first point is the farthest from the centroid
    assert idx[0] == np.argmax(np.linalg.norm(pts - pts.mean(0), axis=1))
    # coverage: every input point lies within the FPS radius (the last selection distance)
    sel = pts[idx]
    cover = np.sqrt(((pts[:, None] - sel[None]) ** 2).sum(-1)).min(1).max()
    assert cover < 0.3  # a 4x4x4 grid has covering radius ~0.22; random picks ~0.5
    # rotation + translation + permutation: FPS picks the same physical points
    R = Rotation.from_euler("zyx", [0.7, -0.3, 1.1]).as_matrix()
    perm = rng.permutation(len(pts))
    moved = (pts @ R.T + np.array([0.3, -2.0, 5.0]))[perm]
    idx2 = fps(moved, 64)
    np.testing.assert_array_equal(perm[idx2], idx)
    # torch batch gives the same indices
    tidx = fps_torch(torch.tensor(np.stack([pts, moved])), 64)
    np.testing.assert_array_equal(tidx[0].numpy(), idx)
    np.testing.assert_array_equal(tidx[1].numpy(), idx2)


def test_fps_errors_name_the_bad_value():
    with pytest.raises(ValueError, match="n=5"):
        fps(np.zeros((3, 3)), 5)
    with pytest.raises(ValueError, match="farthest"):
        fps(np.zeros((3, 3)), 2, start="middle")
    assert fps(np.random.default_rng(0).random((10, 3)), 3, seed=4, start="random")[0] == \
        np.random.default_rng(4).integers(10)
