"""Alpha-expansion with label costs on an arbitrary graph, one PyMaxflow cut per move.

An expansion move on label alpha lets every node either keep its label (s = 0, source side)
or switch to alpha (s = 1, sink side). Its energy is a submodular function of the binary s:

* unary: cost(s=0) = D[k, L_k], cost(s=1) = D[k, alpha];
* Potts edge (i, j) with weight w (Boykov et al. 2001, decomposed as in Kolmogorov & Zabih):
  E00 = w[L_i != L_j], E01 = w[L_i != alpha], E10 = w[alpha != L_j], E11 = 0
  = E00 + (E10 - E00) s_i + (E11 - E10) s_j + (E01 + E10 - E00 - E11) (1 - s_i) s_j,
  the last coefficient >= 0 by the triangle inequality of Potts, so it is an edge i -> j;
* label cost of a label l != alpha in use (Delong et al. 2012, Sec. 3): h_l is paid unless
  every node of l switches, h_l * OR_{k in l}(1 - s_k) = min_y h_l (1 - y) + sum h_l (1 - s_k) y
  with one auxiliary node y (edges k -> y of capacity h_l);
* label cost of alpha: constant over the move when alpha is in use. When it is not, the move's
  energy is F(s) = G(s) + h_alpha [s != 0] with G everything else. Delong's construction adds
  an auxiliary node joined to EVERY node, which makes the BK max-flow ~10x slower; instead we
  minimise G alone by one cut, s*, and use that min F = min(G(0), G(s*) + h_alpha) (s* is the
  global minimiser of G, so it is also the best s != 0 whenever s* != 0; if s* = 0 nothing
  moves). The comparison is the exact-energy acceptance test that follows every move, so the
  move stays optimal over its move space.
* large label-cost stars: BK max-flow slows down badly on a star joined to thousands of nodes
  (a 51 k-node star took 3.9 s, the move 47 ms without it, on a 1280x720 window). The up to
  :data:`MAX_ENUMERATED_STARS` largest stars of at least :data:`ENUMERATED_STAR_MIN_NODES`
  nodes are therefore replaced by enumeration: for each subset R of those labels, cut with
  every node of R forced to alpha (a large sink capacity; successive subsets differ by one
  label, Gray code, and reuse the previous search trees, Kohli & Torr 2005) and keep the
  subset whose cut has the lowest move energy. Exact: if R* is the set of enumerated labels
  the optimal move removes, the cut forced on R* costs at most the optimum (it minimises the
  same energy less the label costs of R*, which it pays no more of), and every evaluated cut is
  scored with its true move energy.

The graph of each move is built with array calls (``add_nodes``, ``add_grid_tedges``,
``add_edges``), never a Python loop over nodes or edges. After each move the exact energy is
computed in numpy (:func:`evseg.segmentation.energy.energy`) and a move that does not lower it
is rejected, so the energy never increases.
"""

from __future__ import annotations

from dataclasses import dataclass

import maxflow
import numpy as np

from evseg.segmentation._kernels import expansion_terms, label_bound_sums
from evseg.segmentation.energy import energy


def expansion_move(
    labels: np.ndarray,
    alpha: int,
    data: np.ndarray,
    edges: np.ndarray,
    edge_w: np.ndarray,
    label_costs: np.ndarray,
) -> np.ndarray:
    """The optimal alpha-expansion of ``labels`` (a new array; the input is not modified).

    Args:
        labels: (M,) int64 current labels in [0, L).
        alpha: the expanding label.
        data: (M, L) data costs. edges: (E, 2) int64. edge_w: (E,) Potts weights >= 0.
        label_costs: (L,) cost h_l >= 0 of each label in use.
    Returns:
        (M,) int64 labels after the move (each node keeps its label or takes alpha).
    """
    labels, data, edges, edge_w = _as_arrays(labels, data, edges, edge_w)
    _check_labels(labels, data.shape[1], int(alpha))
    terms = expansion_terms(labels, int(alpha), data, edges, edge_w)
    return _cut(labels, int(alpha), terms, np.asarray(label_costs, dtype=np.float64))


def _as_arrays(labels, data, edges, edge_w):
    """The dtypes and layouts the compiled move terms expect, checked: the compiled passes
    do not check bounds (called once per function, not per move)."""
    labels = np.ascontiguousarray(labels, dtype=np.int64)
    data = np.ascontiguousarray(data, dtype=np.float64)
    edges = np.ascontiguousarray(np.asarray(edges, dtype=np.int64).reshape(-1, 2))
    edge_w = np.ascontiguousarray(edge_w, dtype=np.float64)
    if data.ndim != 2 or len(data) != len(labels) or len(edge_w) != len(edges):
        raise ValueError(f"expansion: expected data (M, L) and one weight per edge; got {len(labels)} labels, "
                         f"data {data.shape}, {len(edges)} edges, {len(edge_w)} weights")
    _check_labels(labels, data.shape[1])
    if len(edges) and (edges.min() < 0 or edges.max() >= len(labels)):
        raise ValueError(f"expansion: edge ends must lie in [0, {len(labels)}), got [{edges.min()}, {edges.max()}]")
    return labels, data, edges, edge_w


def _check_labels(labels: np.ndarray, n_labels: int, alpha: int | None = None) -> None:
    if len(labels) and (labels.min() < 0 or labels.max() >= n_labels):
        raise ValueError(f"expansion: labels must lie in [0, {n_labels}), got [{labels.min()}, {labels.max()}]")
    if alpha is not None and not 0 <= alpha < n_labels:
        raise ValueError(f"expansion: alpha must lie in [0, {n_labels}), got {alpha}")


MAX_ENUMERATED_STARS = 3
"""At most this many label-cost stars per move are enumerated instead of built (2^k cuts)."""

ENUMERATED_STAR_MIN_NODES = 500
"""A label-cost star is enumerated instead of built when its label holds this many nodes: on
3 k-node windows such labels are rare and the change is neutral (-9 % total cut time on the
1 M events/s benchmark stream); on 52 k-node windows it made the expansion moves 5x faster."""


def _cut(labels: np.ndarray, alpha: int, terms: tuple, label_costs: np.ndarray,
         sums: tuple | None = None) -> np.ndarray:
    """Build the move's graph from its terms (:func:`._kernels.expansion_terms`), cut it.
    ``sums``: :func:`._kernels.label_bound_sums` of the labels and the terms' bound, if known."""
    diff, pair_i, pair_j, pair_w, bound = terms
    m = len(labels)
    n_labels = len(label_costs)
    count, whole, _ = label_bound_sums(labels, bound, n_labels) if sums is None else sums
    others = np.flatnonzero((count > 0) & (label_costs > 0) & (np.arange(n_labels) != alpha))
    if len(others):
        others = others[_label_cost_can_matter(whole, label_costs, others)]
    # The largest stars are enumerated (module docstring), the rest built.
    enumerated = others[np.argsort(-count[others], kind="stable")][:MAX_ENUMERATED_STARS]
    enumerated = np.sort(enumerated[count[enumerated] >= ENUMERATED_STAR_MIN_NODES])
    enumerated_mask = np.zeros(n_labels, dtype=bool)  # not setdiff1d: ~60 us per move on ~10 labels
    enumerated_mask[enumerated] = True
    stars = others[~enumerated_mask[others]]

    g = maxflow.Graph[float](m + len(stars) + 8, len(pair_i) + m)
    nodes = g.add_nodes(m)
    if len(pair_i):
        g.add_edges(pair_i, pair_j, pair_w, np.zeros(len(pair_i)))
    # A node in the source segment (s=0) pays its sink capacity, in the sink segment its source one.
    g.add_grid_tedges(nodes, np.maximum(diff, 0.0), np.maximum(-diff, 0.0))
    if len(stars):
        aux = g.add_nodes(len(stars))
        # y = 0 (source side) pays h_l: sink capacity h_l.
        g.add_grid_tedges(aux, np.zeros(len(stars)), label_costs[stars])
        slot = np.full(n_labels, -1, dtype=np.int64)
        slot[stars] = np.arange(len(stars))
        k = np.flatnonzero(slot[labels] >= 0)
        target = aux[slot[labels[k]]]
        g.add_edges(nodes[k], target, label_costs[labels[k]], np.zeros(len(k)))
    g.maxflow()
    switch = g.get_grid_segments(nodes)
    if len(enumerated):
        switch = _enumerate_stars(g, nodes, switch, labels, enumerated, others, terms, label_costs)
    return np.where(switch, alpha, labels)


def _enumerate_stars(g, nodes, switch, labels, enumerated, others, terms, label_costs):
    """Best cut over the subsets of ``enumerated`` labels forced to alpha (module docstring).

    ``g`` has been cut once (no label forced; that cut is ``switch``); returns the switch mask
    of the subset whose cut has the lowest move energy (first found on ties).
    """
    diff, _, _, pair_w, _ = terms
    # Larger than any energy difference of the move: a forced node never stays.
    force = 1.0 + float(np.abs(diff).sum() + pair_w.sum() + label_costs[others].sum())
    members = [np.flatnonzero(labels == lab) for lab in enumerated]
    forced = np.zeros(len(enumerated), dtype=bool)
    best, best_e = switch, _move_energy(switch, labels, terms, label_costs, others)
    for step in range(1, 2 ** len(enumerated)):
        j = (step & -step).bit_length() - 1  # Gray code: one label changes per step
        forced[j] = not forced[j]
        k = members[j]
        g.add_grid_tedges(nodes[k], np.zeros(len(k)), np.full(len(k), force if forced[j] else -force))
        g.mark_grid_nodes(nodes[k])
        g.maxflow(reuse_trees=True)
        s = g.get_grid_segments(nodes)
        e = _move_energy(s, labels, terms, label_costs, others)
        if e < best_e - 1e-12 * max(1.0, abs(best_e)):
            best, best_e = s, e
    return best


def _move_energy(switch, labels, terms, label_costs, others):
    """Energy of a move (up to a constant) without alpha's label cost: the switched nodes'
    unary terms, the pairwise terms and the label costs of ``others`` still in use."""
    diff, pair_i, pair_j, pair_w, _ = terms
    e = float(diff[switch].sum() + pair_w[~switch[pair_i] & switch[pair_j]].sum())
    kept = np.bincount(labels[~switch], minlength=len(label_costs)) > 0
    return e + float(label_costs[others][kept[others]].sum())


def _label_cost_can_matter(
    per_label: np.ndarray, label_costs: np.ndarray, candidates: np.ndarray,
) -> np.ndarray:
    """Which of the ``candidates`` labels need their label-cost node in this move (bool mask);
    ``per_label`` = the sum of ``bound`` over each label's nodes.

    Label l's auxiliary node only rewards moves that switch *all* of l's nodes to alpha.
    Switching them costs at least sum_{k in l} d_k, d_k = ``bound[k]`` = D[k, alpha] - D[k, l]
    - w_k, with w_k the weight of the edges at k that are cut now (the most Potts energy k's
    switch can remove). If that sum is >= h_l, removing l never pays, and a minimiser of the
    energy without l's node is also a minimiser with it, so the node (joined to every node of
    l: a star that made each max-flow ~6x slower) can be left out and the move stays optimal.
    """
    return per_label[candidates] < label_costs[candidates]


@dataclass(frozen=True)
class ExpansionResult:
    """Labels after alpha-expansion, their exact energy, the max-flows run and moves accepted."""

    labels: np.ndarray
    energy: float
    n_moves: int
    n_accepted: int


def move_cannot_improve(
    labels: np.ndarray, alpha: int, bound: np.ndarray, label_costs: np.ndarray
) -> bool:
    """Exact sufficient test that the expansion on ``alpha`` cannot lower the energy.

    ``bound[k]`` = D[k, alpha] - D[k, L_k] - (weight of the edges cut now at k), as
    :func:`move_bound` gives it. Switching a set S of nodes to alpha changes the Potts energy
    by at least minus the weight of the cut edges touching S, saves h_l only for labels l whose
    nodes all switch, and costs h_alpha if alpha is not in use. So the change is at least
    sum_l min(sum_{k in l} bound_k - h_l, sum_{k in l} min(bound_k, 0)) (+ h_alpha if alpha is
    unused); when that is >= 0 no move lowers the energy and the max-flow can be skipped.
    """
    label_costs = np.asarray(label_costs, dtype=np.float64)
    labels = np.ascontiguousarray(labels, dtype=np.int64)
    _check_labels(labels, len(label_costs), int(alpha))
    bound = np.ascontiguousarray(bound, dtype=np.float64)
    if len(bound) != len(labels):
        raise ValueError(f"move_cannot_improve: {len(bound)} bounds for {len(labels)} labels")
    return _cannot_improve(int(alpha), label_costs, label_bound_sums(labels, bound, len(label_costs)))


def _cannot_improve(alpha: int, label_costs: np.ndarray, sums: tuple) -> bool:
    """:func:`move_cannot_improve` from the per-label sums (:func:`._kernels.label_bound_sums`)."""
    count, whole, part = sums
    present = count > 0
    present[alpha] = False  # alpha's own nodes cannot switch
    if not present.any():
        return True
    least = float(np.minimum(whole - label_costs, part)[present].sum())
    if count[alpha] == 0:  # alpha not in use: any switch pays its label cost
        least += float(label_costs[alpha])
    return least >= 0.0


def move_bound(
    labels: np.ndarray, alpha: int, data: np.ndarray, edges: np.ndarray, edge_w: np.ndarray
) -> np.ndarray:
    """(M,) D[k, alpha] - D[k, L_k] - (weight of the edges cut now at k), the ``bound`` of
    :func:`move_cannot_improve`."""
    labels, data, edges, edge_w = _as_arrays(labels, data, edges, edge_w)
    _check_labels(labels, data.shape[1], int(alpha))
    return expansion_terms(labels, int(alpha), data, edges, edge_w)[4]


def alpha_expansion(
    labels: np.ndarray,
    data: np.ndarray,
    edges: np.ndarray,
    edge_w: np.ndarray,
    label_costs: np.ndarray,
    max_cycles: int = 2,
    order: np.ndarray | None = None,
) -> ExpansionResult:
    """Sweep expansion moves over all labels until a full sweep brings no decrease.

    Args:
        labels: (M,) int start labeling. data: (M, L). edges: (E, 2). edge_w: (E,).
        label_costs: (L,). max_cycles: maximum sweeps. order: labels in sweep order (default
            0..L-1).
    Returns:
        :class:`ExpansionResult`; its energy never exceeds that of the start labeling.
    """
    cur = np.array(labels, dtype=np.int64)
    _, data, edges, edge_w = _as_arrays(cur, data, edges, edge_w)
    label_costs = np.asarray(label_costs, dtype=np.float64)
    n_labels = data.shape[1]
    order = np.arange(n_labels) if order is None else np.asarray(order, dtype=np.int64)
    if len(label_costs) != n_labels or (len(order) and (order.min() < 0 or order.max() >= n_labels)):
        raise ValueError(f"alpha_expansion: {len(label_costs)} label costs and sweep order "
                         f"{order.tolist()} for {n_labels} labels")
    e_cur = energy(cur, data, edges, edge_w, label_costs)
    n_moves = n_acc = 0
    for _ in range(max_cycles):
        improved = False
        for alpha in order:
            terms = expansion_terms(cur, int(alpha), data, edges, edge_w)
            sums = label_bound_sums(cur, terms[4], n_labels)
            if _cannot_improve(int(alpha), label_costs, sums):
                continue
            new = _cut(cur, int(alpha), terms, label_costs, sums)
            n_moves += 1
            if np.array_equal(new, cur):
                continue
            e_new = energy(new, data, edges, edge_w, label_costs)
            # Exact check: the cut is optimal over the move, float round-off is not.
            if e_new < e_cur - 1e-9 * max(1.0, abs(e_cur)):
                cur, e_cur = new, e_new
                improved = True
                n_acc += 1
        if not improved:
            break
    return ExpansionResult(labels=cur, energy=e_cur, n_moves=n_moves, n_accepted=n_acc)
