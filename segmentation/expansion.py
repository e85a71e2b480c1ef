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

The graph of each move is built with array calls (``add_nodes``, ``add_grid_tedges``,
``add_edges``), never a Python loop over nodes or edges. After each move the exact energy is
computed in numpy (:func:`evseg.segmentation.energy.energy`) and a move that does not lower it
is rejected, so the energy never increases.
"""

from __future__ import annotations

from dataclasses import dataclass

import maxflow
import numpy as np

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
    labels = np.asarray(labels, dtype=np.int64)
    m = len(labels)
    ar = np.arange(m)
    cost0 = data[ar, labels]
    cost1 = data[:, alpha].astype(np.float64, copy=True)
    g = maxflow.Graph[float]()
    nodes = g.add_nodes(m)
    if len(edges):
        i, j = edges[:, 0], edges[:, 1]
        li, lj = labels[i], labels[j]
        e00 = edge_w * (li != lj)
        e01 = edge_w * (li != alpha)
        e10 = edge_w * (lj != alpha)
        # Unary parts of the decomposition go to cost(s=1) of the nodes.
        cost1 += np.bincount(i, weights=e10 - e00, minlength=m)
        cost1 -= np.bincount(j, weights=e10, minlength=m)
        pair = e01 + e10 - e00
        nz = pair > 0
        if nz.any():
            g.add_edges(i[nz], j[nz], pair[nz], np.zeros(int(nz.sum())))
    diff = cost1 - cost0
    # A node in the source segment (s=0) pays its sink capacity, in the sink segment its source one.
    g.add_grid_tedges(nodes, np.maximum(diff, 0.0), np.maximum(-diff, 0.0))

    n_labels = len(label_costs)
    used = np.bincount(labels, minlength=n_labels) > 0
    others = np.flatnonzero(used & (label_costs > 0) & (np.arange(n_labels) != alpha))
    if len(others) and len(edges):
        others = others[_label_cost_can_matter(labels, alpha, data, edges, edge_w, label_costs, others)]
    if len(others):
        aux = g.add_nodes(len(others))
        h = label_costs[others]
        # y = 0 (source side) pays h_l: sink capacity h_l.
        g.add_grid_tedges(aux, np.zeros(len(others)), h)
        slot = np.full(n_labels, -1, dtype=np.int64)
        slot[others] = np.arange(len(others))
        k = np.flatnonzero(slot[labels] >= 0)
        target = aux[slot[labels[k]]]
        g.add_edges(nodes[k], target, label_costs[labels[k]], np.zeros(len(k)))
    g.maxflow()
    switch = g.get_grid_segments(nodes)
    return np.where(switch, alpha, labels)


def _label_cost_can_matter(
    labels: np.ndarray, alpha: int, data: np.ndarray, edges: np.ndarray, edge_w: np.ndarray,
    label_costs: np.ndarray, candidates: np.ndarray,
) -> np.ndarray:
    """Which of the ``candidates`` labels need their label-cost node in this move (bool mask).

    Label l's auxiliary node only rewards moves that switch *all* of l's nodes to alpha.
    Switching them costs at least sum_{k in l} d_k, d_k = D[k, alpha] - D[k, l] - w_k, with
    w_k the weight of the edges at k that are cut now (the most Potts energy k's switch can
    remove). If that sum is >= h_l, removing l never pays, and a minimiser of the energy without
    l's node is also a minimiser with it, so the node (joined to every node of l: a star that
    made each max-flow ~6x slower) can be left out and the move stays optimal.
    """
    i, j = edges[:, 0], edges[:, 1]
    cut = edge_w * (labels[i] != labels[j])
    m = len(labels)
    w_k = np.bincount(i, weights=cut, minlength=m) + np.bincount(j, weights=cut, minlength=m)
    d = data[np.arange(m), alpha] - data[np.arange(m), labels] - w_k
    per_label = np.bincount(labels, weights=d, minlength=len(label_costs))
    return per_label[candidates] < label_costs[candidates]


@dataclass(frozen=True)
class ExpansionResult:
    """Labels after alpha-expansion, their exact energy, the max-flows run and moves accepted."""

    labels: np.ndarray
    energy: float
    n_moves: int
    n_accepted: int


def move_cannot_improve(
    labels: np.ndarray, alpha: int, data: np.ndarray, cut_weight: np.ndarray, label_costs: np.ndarray
) -> bool:
    """Exact sufficient test that the expansion on ``alpha`` cannot lower the energy.

    For a set S of nodes switching to alpha, the Potts energy can drop at most by the weights
    of the edges cut now and touching S (``cut_weight`` per node, (M,)), and label costs only
    drop for labels whose nodes all switch. With d_k = D[k, alpha] - D[k, L_k] - cut_weight[k],
    if d_k > 0 for every node not labelled alpha and sum_{k in l} d_k >= h_l for every label l,
    every S raises the energy, so the max-flow can be skipped.
    """
    rows = np.flatnonzero(labels != alpha)
    if len(rows) == 0:
        return True
    lab = labels[rows]
    d = data[rows, alpha] - data[rows, lab] - cut_weight[rows]
    if not np.all(d > 0):
        return False
    per_label = np.bincount(lab, weights=d, minlength=len(label_costs))
    present = np.bincount(lab, minlength=len(label_costs)) > 0
    return bool(np.all(per_label[present] >= label_costs[present]))


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
    e_cur = energy(cur, data, edges, edge_w, label_costs)
    n_labels = data.shape[1]
    order = np.arange(n_labels) if order is None else np.asarray(order, dtype=np.int64)
    n_moves = n_acc = 0
    for _ in range(max_cycles):
        improved = False
        for alpha in order:
            if len(edges):
                cut = edge_w * (cur[edges[:, 0]] != cur[edges[:, 1]])
                cut_weight = (np.bincount(edges[:, 0], weights=cut, minlength=len(cur))
                              + np.bincount(edges[:, 1], weights=cut, minlength=len(cur)))
            else:
                cut_weight = np.zeros(len(cur))
            if move_cannot_improve(cur, int(alpha), data, cut_weight, label_costs):
                continue
            new = expansion_move(cur, int(alpha), data, edges, edge_w, label_costs)
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
