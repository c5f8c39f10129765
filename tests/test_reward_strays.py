"""A piece's body (topocut.reward.strays, docs/reward.md#strays): a thread of particles the blade dragged out of a
piece is left out of what the reward describes; a piece without one is described whole."""
import numpy as np
import pytest

from topocut.reward import RewardConfig, piece_distance, spectral_reward
from topocut.reward.strays import body

H = 0.004  # lattice spacing


def box(a, b, c, seed=0, h=H):
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.arange(h / 2, s, h) for s in (a, b, c)], indexing="ij"), -1).reshape(-1, 3)
    return g + rng.uniform(-h / 4, h / 4, g.shape)  # the simulator's jittered lattice (+-0.25 spacing per axis)


def with_thread(p, n, h=H, seed=1):
    """p and a one-particle thread of n particles, h apart, leaving the middle of its +x face along +x (a drag)."""
    rng = np.random.default_rng(seed)
    face = p[:, 0].max()
    mid = np.median(p[:, 1:], axis=0)
    t = np.stack([face + h * np.arange(1, n + 1), np.full(n, mid[0]), np.full(n, mid[1])], -1)
    return np.concatenate([p, t + rng.uniform(-h / 8, h / 8, t.shape)])


@pytest.mark.parametrize("dims", [(0.03, 0.03, 0.03), (0.1, 0.03, 0.008), (0.06, 0.06, 0.004), (0.03, 0.012, 0.012)])
def test_a_piece_without_strays_is_its_own_body(dims):
    """A die, a two-layer slab, a one-layer sheet and a stick keep every particle: corners and edges are one link
    from the core (their neighbour counts, 3-9, are the rim's)."""
    p = box(*dims)
    assert len(body(p, H, 0.05)) == len(p)


def test_a_dragged_thread_is_left_out_but_its_first_link_stays():
    p = box(0.03, 0.03, 0.03)
    q = with_thread(p, 6)
    kept = body(q, H, 0.05)
    # the thread's particles past the first link from the face's core are gone; the die is whole
    assert len(p) <= len(kept) <= len(p) + 2
    assert (kept[:, 0] <= p[:, 0].max() + 2 * H + 1e-9).all()


def test_a_die_with_a_thread_scores_as_the_die_and_without_the_rule_it_does_not():
    """The case that made this rule (dice / potato / 0 at 128^3 on the H200): 5-10 dragged particles in a
    thread took a perfect die from R 1 to 0.  A die 7.5 spacings wide and a 6-particle thread (2.4% of it)."""
    goal = box(0.03, 0.03, 0.03)
    frag = with_thread(box(0.03, 0.03, 0.03, seed=3), 6)
    d_with = piece_distance(frag, goal, RewardConfig())
    d_without = piece_distance(frag, goal, RewardConfig(stray_share=0.0))
    assert d_with < 0.02 < 0.1 < d_without
    r = spectral_reward([frag], [goal], RewardConfig())
    assert r.total > 0.95 and r.cut_count == 1
    assert spectral_reward([frag], [goal], RewardConfig(stray_share=0.0)).total < 0.75


def test_more_strays_than_the_share_leave_the_piece_whole():
    """A thread of 8% of the piece is no crumb: nothing is left out and the piece is scored as it is."""
    p = box(0.02, 0.02, 0.02)  # 125 particles
    q = with_thread(p, 10)
    assert len(body(q, H, 0.05)) == len(q)
    assert len(body(q, H, 0.10)) < len(q)


def test_a_wrong_piece_stays_wrong():
    """The body does not rescue a wrong cut: a die 1.5x too long is as far from the goal with the rule as without."""
    goal = box(0.03, 0.03, 0.03)
    long = box(0.045, 0.03, 0.03, seed=2)
    assert piece_distance(long, goal, RewardConfig()) == pytest.approx(piece_distance(long, goal,
                                                                                      RewardConfig(stray_share=0.0)))
    assert spectral_reward([long], [goal], RewardConfig()).cut_count == 0
