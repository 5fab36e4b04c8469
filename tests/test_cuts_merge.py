"""The light tree's post-order arithmetic, cut selection and the batched cut merge (Cheslack-Postava et al. 2008, 3.2),
checked against a plain Python transcription of the paper's single-traversal merge loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relight_torch.cuts.cuts import Cuts, cuts_from_mask, intensity_cut, variance_cut_mask
from relight_torch.cuts.merge import merge, refine
from relight_torch.cuts.tree import LightTree


def _postorder_reference(num_leaves: int) -> tuple[list[int], list[int]]:
    """(leftleaf, size) per post-order index, by an explicit recursive traversal."""
    leftleaf, size = [], []

    def visit(first: int, count: int) -> int:
        if count == 1:
            leftleaf.append(len(leftleaf))
            size.append(1)
            return len(leftleaf) - 1
        left = visit(first, count // 2)
        visit(first + count // 2, count // 2)
        leftleaf.append(leftleaf[left])
        size.append(count)
        return len(leftleaf) - 1

    visit(0, num_leaves)
    return leftleaf, size


def test_tree_indices_match_a_postorder_traversal():
    tree = LightTree.of(64)
    leftleaf, size = _postorder_reference(64)
    assert tree.leftleaf.tolist() == leftleaf
    assert tree.size.tolist() == size
    values = torch.arange(64, dtype=torch.float64)
    sums = tree.aggregate(values)
    leaf_of_node = torch.searchsorted(tree.leaf_nodes, tree.leftleaf)  # leftmost leaf number
    expected = torch.stack(
        [values[int(m) : int(m) + int(s)].sum() for m, s in zip(leaf_of_node, tree.size, strict=True)]
    )
    assert torch.equal(sums, expected)
    assert torch.equal(tree.aggregate_batch(values[None]), sums[None])
    with pytest.raises(ValueError, match="power-of-two"):
        LightTree.of(48)


def _random_cut(tree: LightTree, rng: np.random.Generator, split_probability: float) -> list[int]:
    """A random cut: from the root, split each node with `split_probability`; sorted nodes."""
    nodes, stack = [], [tree.root]
    height = tree.height.tolist()
    while stack:
        node = stack.pop()
        h = height[node]
        if h > 0 and rng.random() < split_probability:
            stack += [node - (1 << h), node - 1]
        else:
            nodes.append(node)
    return sorted(nodes)


def _paper_merge_loop(
    tree: LightTree,
    cuts: list[list[int]],
    values: list[list[float]],
    weights: list[float],
    light_nodes: list[int],
    light_values: list[float],
) -> float:
    """Cheslack-Postava et al. 2008's merge loop, transcribed: sum over merged clusters of
    |C| <l> (sum_j w_j <v_j>) f(node),
    with f(node) = 1 + node / 1000 standing in for the BRDF at the cluster's mean direction."""
    leftleaf, size = tree.leftleaf.tolist(), tree.size.tolist()
    all_cuts = cuts + [light_nodes]
    pointers = [0] * len(all_cuts)
    total = 0.0
    while True:
        current = [cut[p] for cut, p in zip(all_cuts, pointers, strict=True)]
        min_index = min(current)
        max_leftleaf = max(leftleaf[n] for n in current)
        if max_leftleaf <= min_index:  # all current nodes overlap
            visibility = sum(w * values[j][pointers[j]] for j, w in enumerate(weights))
            total += size[min_index] * light_values[pointers[-1]] * visibility * (1.0 + min_index / 1000.0)
        done = False
        for j, node in enumerate(current):
            if node == min_index:
                pointers[j] += 1
                if pointers[j] >= len(all_cuts[j]):
                    done = True
        if done:
            return total


@pytest.mark.parametrize("num_sources", [1, 2, 3])
def test_batched_merge_matches_the_paper_loop(num_sources):
    rng = np.random.default_rng(num_sources)
    tree = LightTree.of(256)
    num_cuts, num_rows = 40, 60
    cut_lists = [_random_cut(tree, rng, rng.uniform(0.3, 0.95)) for _ in range(num_cuts)]
    value_lists = [list(rng.random(len(c))) for c in cut_lists]
    counts = torch.tensor([len(c) for c in cut_lists])
    cuts = Cuts(
        torch.cat((torch.zeros(1, dtype=torch.int64), counts.cumsum(0))),
        torch.tensor([index for cut in cut_lists for index in cut]),
        torch.tensor([value for values in value_lists for value in values], dtype=torch.float64),
    )
    cuts.check(tree)
    rows = torch.from_numpy(rng.integers(0, num_cuts, (num_rows, num_sources)))
    weights = torch.from_numpy(rng.dirichlet(np.ones(num_sources), num_rows))
    light = torch.tensor(_random_cut(tree, rng, 0.8))
    light_values = torch.from_numpy(rng.random(light.shape[0]))

    merged = refine(tree, merge(tree, [(cuts, rows[:, j]) for j in range(num_sources)]), light)
    visibility = sum(weights[merged.row, j] * cuts.values[merged.cover[j]] for j in range(num_sources))
    terms = tree.size[merged.node] * light_values[merged.cover[-1]] * visibility * (1.0 + merged.node.double() / 1000.0)
    batched = torch.zeros(num_rows, dtype=torch.float64).index_add_(0, merged.row, terms)

    for p in range(num_rows):
        expected = _paper_merge_loop(
            tree,
            [cut_lists[r] for r in rows[p].tolist()],
            [value_lists[r] for r in rows[p].tolist()],
            weights[p].tolist(),
            light.tolist(),
            light_values.tolist(),
        )
        assert batched[p].item() == pytest.approx(expected, rel=1e-12)
    # The merged cut of a row is a sorted partition of the leaves.
    sizes = torch.bincount(merged.row, minlength=num_rows)
    Cuts(torch.cat((sizes.new_zeros(1), sizes.cumsum(0))), merged.node, merged.node[:, None]).check(tree)


def test_variance_cuts_bound_every_node_and_are_minimal():
    rng = np.random.default_rng(5)
    tree = LightTree.of(512)
    visible = torch.from_numpy(rng.random((8, 512)) < np.linspace(0.0, 1.0, 512)).double()
    means = tree.aggregate_batch(visible) / tree.size
    variances = means * (1.0 - means)
    sigma = 2.0
    mask = variance_cut_mask(tree, variances, sigma)
    cuts = cuts_from_mask(mask, means[..., None])
    cuts.check(tree)
    chosen = cuts.nodes
    error = tree.size[chosen] * variances[torch.repeat_interleave(torch.arange(8), cuts.sizes()), chosen]
    assert bool((error <= sigma**2).all())
    # Minimal: every strict ancestor of a cut node violates the bound (checked on the parents).
    height = tree.height[chosen]
    parents = torch.where(chosen + 1 < tree.num_nodes, chosen + 1, chosen)  # right children's parent
    right_child = (height < tree.height[parents]) & (parents != chosen)
    rows = torch.repeat_interleave(torch.arange(8), cuts.sizes())
    assert bool((tree.size[parents] * variances[rows, parents] > sigma**2)[right_child].all())


def test_intensity_cut_refines_the_brightest_nodes_up_to_its_size():
    tree = LightTree.of(1024)
    leaf = torch.full((1024,), 0.01, dtype=torch.float64)
    leaf[700] = 100.0
    nodes = intensity_cut(tree, tree.aggregate(leaf), 32)
    assert nodes.shape[0] == 32
    assert tree.leaf_nodes[700].item() in nodes.tolist()  # the bright light is isolated
    Cuts(torch.tensor([0, 32]), nodes, nodes[:, None]).check(tree)
    assert intensity_cut(tree, tree.aggregate(leaf), 1).tolist() == [tree.root]
