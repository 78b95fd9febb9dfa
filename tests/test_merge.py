"""Cluster merge and remaps: exact clusters, conserved mass, consistent optimiser state."""

import numpy as np
import torch

from gaussian_atoms_method.atoms.merge import cluster_labels, merged_values
from gaussian_atoms_method.density.remap import apply_remap, duplicate_remap, keep_remap
from gaussian_atoms_method.physics.projector import gaussian_mass


def test_clusters_follow_chains_and_threshold():
    # 0-1-2 form a chain of 0.2 steps (0 and 2 are 0.4 apart: linked through 1); 3 is alone.
    pos = np.array([[0, 0, 0], [0.2, 0, 0], [0.4, 0, 0], [5, 5, 5]], float)
    labels, n = cluster_labels(pos, 0.25)
    assert n == 2 and labels[0] == labels[1] == labels[2] != labels[3]
    labels, n = cluster_labels(pos, 0.19)
    assert n == 4


def test_clusters_many_points_exact():
    """Compare with brute-force connected components on random points."""
    rng = np.random.default_rng(0)
    pos = rng.uniform(0, 5, size=(300, 3))
    labels, n = cluster_labels(pos, 0.4)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) <= 0.4
    # Brute-force transitive closure.
    reach = d.copy()
    for _ in range(300):
        new = (reach.astype(int) @ d.astype(int)) > 0
        if (new == reach).all():
            break
        reach = new
    same = labels[:, None] == labels[None]
    assert (same == reach).all()


def test_merge_conserves_mass_or_averages():
    means = torch.tensor([[0.0, 0, 0], [0.2, 0, 0], [3.0, 0, 0]])
    sigmas = torch.tensor([0.5, 0.7, 0.6])
    amps = torch.tensor([2.0, 1.0, 4.0])
    labels = torch.tensor([0, 0, 1])
    m, s, a = merged_values(means, sigmas, amps, labels, 2, "mass")
    # Mass-weighted: masses 2 * 0.5^3 = 0.25 and 1 * 0.7^3 = 0.343 (times (2 pi)^1.5).
    w = torch.tensor([0.25, 0.343]) / 0.593
    torch.testing.assert_close(m[0], torch.tensor([float(w[1]) * 0.2, 0.0, 0.0]))
    torch.testing.assert_close(s, torch.tensor([float(w[0] * 0.5 + w[1] * 0.7), 0.6]))
    torch.testing.assert_close(gaussian_mass(s, a)[0], gaussian_mass(sigmas[:2], amps[:2]).sum())
    torch.testing.assert_close(a[1], amps[2])
    m_mean, s_mean, a_mean = merged_values(means, sigmas, amps, labels, 2, "mean")
    torch.testing.assert_close(a_mean, torch.tensor([1.5, 4.0]))  # the paper's rule: plain means
    torch.testing.assert_close(m_mean[0], torch.tensor([0.1, 0.0, 0.0]))
    torch.testing.assert_close(s_mean, torch.tensor([0.6, 0.6]))


def _params_and_adam(n=5):
    torch.manual_seed(0)
    params = torch.nn.ParameterDict(
        {"means": torch.nn.Parameter(torch.randn(n, 3)), "log_sigmas": torch.nn.Parameter(torch.randn(n, 1))}
    )
    opts = {k: torch.optim.Adam([p], lr=0.1) for k, p in params.items()}
    loss = sum((p**2).sum() for p in params.values())
    loss.backward()
    for o in opts.values():
        o.step()
    return params, opts


def test_remap_keeps_optimizer_state_consistent():
    params, opts = _params_and_adam()
    old_means = params["means"].data.clone()
    old_state = {k: v.clone() for k, v in opts["means"].state[params["means"]].items() if v.dim() > 0}
    keep = torch.tensor([True, False, True, True, False])
    lists = {"means": [params["means"]]}
    apply_remap(params, opts, *keep_remap(keep), param_lists=lists)
    new = params["means"]
    assert new.shape == (3, 3) and lists["means"][0] is new
    torch.testing.assert_close(new.data, old_means[keep])
    state = opts["means"].state[new]
    for k, v in old_state.items():
        torch.testing.assert_close(state[k], v[keep])
    assert opts["means"].param_groups[0]["params"][0] is new
    # The optimiser still steps the new parameter.
    new.grad = torch.ones_like(new)
    before = new.data.clone()
    opts["means"].step()
    assert not torch.equal(before, new.data)


def test_duplicate_and_merge_remap_average_state():
    params, opts = _params_and_adam(4)
    sq = opts["means"].state[params["means"]]["exp_avg_sq"].clone()
    apply_remap(params, opts, *duplicate_remap(4, torch.tensor([1, 3])))
    assert params["means"].shape == (6, 3)
    torch.testing.assert_close(opts["means"].state[params["means"]]["exp_avg_sq"][4:], sq[[1, 3]])
    # Merge rows 0 and 1 into one: moments become their mean.
    sq = opts["means"].state[params["means"]]["exp_avg_sq"].clone()
    labels = torch.tensor([0, 0, 1, 2, 3, 4])
    apply_remap(params, opts, torch.arange(6), labels, 5)
    torch.testing.assert_close(opts["means"].state[params["means"]]["exp_avg_sq"][0], sq[:2].mean(0))


def test_disjoint_pairs_never_chain():
    """A-B, B-C and C-D all linked (E alone): connected components would make one cluster of
    four; the greedy disjoint pairs (best first) merge A-B and C-D, and B-C is not taken."""
    import numpy as np

    from gaussian_atoms_method.atoms.merge import disjoint_pair_labels

    labels, n = disjoint_pair_labels(5, np.array([[0, 1], [1, 2], [2, 3]]))
    assert n == 3 and labels[0] == labels[1] and labels[2] == labels[3] and len({labels[1], labels[2], labels[4]}) == 3
    labels, n = disjoint_pair_labels(4, np.array([[1, 2], [0, 1], [2, 3]]))
    assert n == 3 and labels[1] == labels[2] and len({labels[0], labels[1], labels[3]}) == 3
    assert disjoint_pair_labels(3, np.zeros((0, 2), dtype=np.int64))[1] == 3


def test_clusters_found_in_torch_are_the_k_d_trees():
    """:func:`cluster_labels_on_device` (what a GPU run takes; here on the CPU) gives the k-d
    tree's clusters with scipy's numbering, on random clouds of chains and lone points, with and
    without a mergeable mask."""
    import torch

    from gaussian_atoms_method.atoms.merge import cluster_labels_on_device

    rng = np.random.default_rng(7)
    for n, side, threshold in ((1, 1.0, 0.3), (400, 4.0, 0.35), (2500, 12.0, 0.5), (2500, 6.0, 0.4)):
        pos = (rng.random((n, 3)) * side).astype(np.float32)
        mergeable = rng.random(n) > 0.25
        for mask in (None, mergeable):
            expected = cluster_labels(pos, threshold, mask)
            labels, count = cluster_labels_on_device(
                torch.tensor(pos), threshold, None if mask is None else torch.tensor(mask)
            )
            assert count == expected[1] and np.array_equal(labels, expected[0])
