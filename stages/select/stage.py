"""Selection of the final paths by a binary program (paper §4.3 "Extracting final paths").

One binary ``e_p`` per candidate (allowed) path; minimise ``Σ_p c_p e_p`` with ``c_p`` the Eq. 6a
energy of the *flowed* path (flow artifact ``energies``), subject to

* **valence** — for every keypoint k that ends or is passed through by a candidate:
  ``Σ_p a_pk e_p ≥ min(available_k, r_k)``, where ``a_pk`` is the number of ends of p at k plus 2 for
  each time p runs *through* k (topology ``through_keypoints``), ``available_k = Σ_p a_pk`` and
  ``r_k`` = 1 / 2 / 3 for endpoints / sharp corners / junctions (config ``valence``);
* **coverage** — every band pixel covered by some candidate (topology ``coverage``) is covered by at
  least one chosen path: ``Σ_{p ∋ pixel} e_p ≥ 1``.

Solved with CBC through pulp (``PULP_CBC_CMD``) with a time limit, one independent block at a time.

Choices made on purpose
-----------------------
* **Order.**  The MIP runs after the flow over the flowed curves, as in the authors' code (the paper
  describes it before the flow); the costs are flow energies, so a λ sweep re-runs flow → select.
* **Valences capped by what is available** (``cap_valence``, authors' code and paper §4.2 "avoiding
  infeasible optimization by adjusting the necessary valences"): a junction with only two candidate
  path ends cannot demand three.  With the cap the program is always feasible (choosing every
  candidate satisfies it).  Synthetic ends (``end_keypoints`` < 0) carry no constraint.
* **Endpoints and corners: curve ends, softly bounded.**  A path running *through* an endpoint
  keypoint (topology ``pass_through_endpoints``) is another stroke passing by and gives it no
  valence.  Curve ends beyond ``max_ends`` (1 at an endpoint, 2 at a corner) cost
  ``excess_penalty`` each (a continuous slack per keypoint): a stroke ends once.  Without it, a
  stroke passing an endpoint was cut there (three ends on one endpoint, scored as a junction).
* **A cost per curve** (``curve_cost``, added to every energy) breaks the near-ties between one
  path through a junction and its two halves in favour of the longer curve; the halves left short
  dangling pieces beyond crossings.
* **Branch cap** (``cap_branches``, off by default): the required valence may also be capped by
  the covering subgraph's branches at the keypoint (topology ``keypoint_branches``).  It removes
  duplicated curves at junction keypoints that only a loop passes, but the ground truth of
  realvec_dev labels overdrawn, overlapping strokes as junctions, and there the duplicates score:
  junction F1 fell from 0.833 to 0.821 (median) with it.
* **Pixels with the same set of covering paths give one constraint** (identical rows are redundant);
  this shrinks the program by one to two orders of magnitude on drawings.
* **Independent blocks in programs of bounded size** (paths linked by no row, packed in order up to
  ``PROGRAM_PATHS``): a page of many drawings is a sum of small programs, linear in its blocks, where
  one program over all of them hit ``time_limit``; one drawing is still the one program it was (a
  program per block cost ~15 ms each); among equally good answers CBC's tie pick is its program's.
* **Fallback, never "all curves".**  The authors return every candidate when Gurobi fails.  We use a
  greedy rule whenever CBC reports infeasibility, finds no integer solution within ``time_limit``, or
  errs, or its answer violates a constraint (checked): (1) for each keypoint, in order of id, add its
  cheapest incident candidates until its (capped) valence is met; (2) weighted set cover: repeatedly
  add the candidate with the least cost per newly covered pixel; (3) prune: drop chosen paths, most
  expensive first, whose removal keeps every constraint satisfied.  With ``cap_valence: false`` the
  fallback still honours the *capped* valences.  ``status`` tells which happened:
  ``optimal``, ``feasible`` (time limit hit with an integer solution, which is used),
  ``fallback: <reason>`` or ``empty``.

References
----------
.. [1] I. Puhachov, W. Neveu, E. Chien, M. Bessmeltsev, "Keypoint-Driven Line Drawing Vectorization
       via PolyVector Flow", ACM Trans. Graph. 40(6), 2021, §4.3.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from stages.artifact import Artifact, unpack_ragged
from stages.config import from_section
from stages.errors import InputError
from stages.select import SelectConfig


@dataclass
class SelectionProblem:
    """The binary program in matrix form (rows are ``≥`` constraints on the 0/1 path vector).

    Attributes
    ----------
    cost : numpy.ndarray
        (P,) path costs.
    valence : scipy.sparse.csr_matrix
        (K, P) incidences ``a_pk`` of the constrained keypoints; ``valence_rhs`` (K,) their demands and
        ``valence_capped`` (K,) the demands capped by availability; ``keypoints`` (K,) their ids.
    cover : scipy.sparse.csr_matrix
        (C, P) 0/1: one row per distinct set of paths covering some pixel; ``cover_pixels`` (C,) how
        many pixels share each row.
    """

    cost: np.ndarray
    valence: sp.csr_matrix
    valence_rhs: np.ndarray
    valence_capped: np.ndarray
    keypoints: np.ndarray
    cover: sp.csr_matrix
    cover_pixels: np.ndarray
    ends: sp.csr_matrix = None
    ends_max: np.ndarray = None
    ends_keypoints: np.ndarray = None
    excess_penalty: float = 0.0

    def penalty(self, chosen: np.ndarray) -> float:
        """Soft upper-bound penalty of a 0/1 choice: ``excess_penalty`` per curve end beyond ``ends_max``."""
        if self.ends is None or self.ends.shape[0] == 0:
            return 0.0
        over = np.asarray(self.ends @ np.asarray(chosen, np.float64)).ravel() - self.ends_max
        return float(self.excess_penalty * np.maximum(over, 0.0).sum())


def build_problem(paths: list[dict], coverage: list[np.ndarray], cost: np.ndarray,
                  keypoint_types: dict[int, int], params: SelectConfig,
                  branches: dict[int, int] | None = None) -> SelectionProblem:
    """Assemble valence and coverage constraints.

    Parameters
    ----------
    paths : list of dict
        Topology ``paths`` (``end_keypoints``, optional ``through_keypoints``).
    coverage : list of numpy.ndarray
        Per path, flat band-pixel indices it covers.
    cost : numpy.ndarray
        (P,) costs.
    keypoint_types : dict of int to int
        Keypoint id → type code (1/3/5); keypoints of other types are not constrained.
    params : SelectConfig
    branches : dict of int to int, optional
        Keypoint id → number of covering-subgraph branches leaving it (topology
        ``keypoint_branches``); the required valence is capped by it too.

    Returns
    -------
    SelectionProblem
    """
    npath = len(paths)
    branches = branches or {}
    rows, cols, thr = [], [], []
    for j, p in enumerate(paths):
        for k in p.get("end_keypoints", []):
            if int(k) >= 0:
                rows.append(int(k))
                cols.append(j)
                thr.append(False)
        for k in p.get("through_keypoints", []) or []:
            if int(k) >= 0:
                rows += [int(k), int(k)]
                cols += [j, j]
                thr += [True, True]
    valence, max_ends = params.valence_by_type(), params.max_ends_by_type()
    kps = np.array(sorted({k for k in rows if keypoint_types.get(k) in valence}), np.int64)
    index = {int(k): i for i, k in enumerate(kps)}
    # A path running through an *endpoint* is another stroke passing by: it gives the endpoint no valence.
    keep = [i for i, k in enumerate(rows) if k in index and not (thr[i] and keypoint_types[k] == 1)]
    a = sp.csr_matrix((np.ones(len(keep)), ([index[rows[i]] for i in keep], [cols[i] for i in keep])),
                      shape=(len(kps), npath))
    a.sum_duplicates()
    need = np.array([valence[keypoint_types[int(k)]] for k in kps], np.float64)
    available = np.asarray(a.sum(axis=1)).ravel()
    branch = np.array([branches.get(int(k), np.inf) if params.cap_branches else np.inf for k in kps], np.float64)
    capped = np.minimum(np.minimum(need, available), branch)
    # Soft upper bounds on the curve ends at endpoints and corners.
    ek = np.array([k for k in kps if keypoint_types[int(k)] in max_ends], np.int64)
    eindex = {int(k): i for i, k in enumerate(ek)}
    ekeep = [i for i, k in enumerate(rows) if k in eindex and not thr[i]]
    ends = sp.csr_matrix((np.ones(len(ekeep)), ([eindex[rows[i]] for i in ekeep], [cols[i] for i in ekeep])),
                         shape=(len(ek), npath))
    ends.sum_duplicates()
    ends_max = np.array([max_ends[keypoint_types[int(k)]] for k in ek], np.float64)

    # Coverage: pixel → set of covering paths; one row per distinct set.
    counts = np.array([len(c) for c in coverage], np.int64)
    pix = np.concatenate(coverage).astype(np.int64) if npath else np.zeros(0, np.int64)
    pid = np.repeat(np.arange(npath), counts)
    order = np.lexsort((pid, pix))
    pix, pid = pix[order], pid[order]
    first = np.ones(len(pix), bool)
    first[1:] = (pix[1:] != pix[:-1]) | (pid[1:] != pid[:-1])
    pix, pid = pix[first], pid[first]
    start = np.flatnonzero(np.r_[True, pix[1:] != pix[:-1]]) if len(pix) else np.zeros(0, np.int64)
    group = np.cumsum(np.r_[True, pix[1:] != pix[:-1]]) - 1 if len(pix) else np.zeros(0, np.int64)
    # Two independent random 64-bit keys per path: equal sets ⇔ equal key sums (collisions ~2⁻¹²⁸).
    rng = np.random.default_rng(12345)
    keys = rng.integers(0, 2 ** 63, size=(npath, 2), dtype=np.uint64) if npath else np.zeros((0, 2), np.uint64)
    sig = np.zeros((len(start), 2), np.uint64)
    with np.errstate(over="ignore"):
        np.add.at(sig, group, keys[pid])
    sizes = np.diff(np.r_[start, len(pix)])
    signature = np.concatenate([sig, sizes[:, None].astype(np.uint64)], axis=1)
    _, rep, mult = np.unique(signature, axis=0, return_index=True, return_counts=True)
    row_of_group = np.full(len(start), -1)
    row_of_group[rep] = np.arange(len(rep))
    sel = row_of_group[group] >= 0
    cover = sp.csr_matrix((np.ones(int(sel.sum())), (row_of_group[group][sel], pid[sel])),
                          shape=(len(rep), npath))
    return SelectionProblem(cost=np.asarray(cost, np.float64), valence=a, valence_rhs=need,
                            valence_capped=capped, keypoints=kps, cover=cover, cover_pixels=mult,
                            ends=ends, ends_max=ends_max, ends_keypoints=ek, excess_penalty=params.excess_penalty)


def satisfies(problem: SelectionProblem, chosen: np.ndarray, capped: bool = True) -> bool:
    """Whether a 0/1 choice meets every coverage and (capped or plain) valence constraint."""
    x = np.asarray(chosen, np.float64)
    rhs = problem.valence_capped if capped else problem.valence_rhs
    ok_v = bool(np.all(problem.valence @ x >= rhs - 1e-9))
    ok_c = bool(np.all(problem.cover @ x >= 1 - 1e-9))
    return ok_v and ok_c


def greedy_selection(problem: SelectionProblem) -> np.ndarray:
    """The documented fallback: valences first, then weighted set cover, then pruning.

    Returns
    -------
    numpy.ndarray
        bool (P,) choice that satisfies the coverage and the *capped* valence constraints.
    """
    npath = len(problem.cost)
    cost = np.maximum(problem.cost, 1e-12)
    x = np.zeros(npath, bool)
    a = problem.valence.tocsr()
    # (1) Valences: cheapest incident candidates first, keypoints in id order.
    for i in range(a.shape[0]):
        lo, hi = a.indptr[i], a.indptr[i + 1]
        inc, mult = a.indices[lo:hi], a.data[lo:hi]
        have = float(mult[x[inc]].sum())
        for j in np.argsort(cost[inc], kind="stable"):
            if have >= problem.valence_capped[i] - 1e-9:
                break
            if not x[inc[j]]:
                x[inc[j]] = True
                have += mult[j]
    # (2) Weighted set cover over the distinct pixel sets (weighted by their pixel counts).
    cov_t = problem.cover.T.tocsr()
    uncovered = np.asarray(problem.cover @ x.astype(float)).ravel() < 0.5
    while uncovered.any():
        gain = cov_t @ (uncovered * problem.cover_pixels).astype(float)
        gain[x] = 0
        if not np.any(gain > 0):
            break  # cannot happen: every row has a covering path
        j = int(np.argmin(np.where(gain > 0, cost / np.maximum(gain, 1e-300), np.inf)))
        x[j] = True
        uncovered &= ~(np.asarray(problem.cover[:, j].todense()).ravel() > 0)
    # (3) Prune redundant paths, most expensive first.
    for j in np.argsort(-cost, kind="stable"):
        if x[j]:
            x[j] = False
            if not satisfies(problem, x, capped=True):
                x[j] = True
    return x


def solve_mip(problem: SelectionProblem, params: SelectConfig) -> tuple[np.ndarray | None, str, float | None]:
    """Solve the binary program with CBC.

    Returns
    -------
    chosen : numpy.ndarray or None
        bool (P,), or None when CBC gave no usable integer solution.
    status : str
        ``optimal``, ``feasible`` (time limit with an integer solution), ``infeasible``,
        ``no_solution`` or ``solver_error: …``.
    objective : float or None
    """
    import pulp

    npath = len(problem.cost)
    prob = pulp.LpProblem("select_paths", pulp.LpMinimize)
    x = [prob.add_variable(f"e{j}", 0, 1, cat=pulp.LpBinary) for j in range(npath)]
    prob += pulp.lpSum(float(c) * v for c, v in zip(problem.cost, x))
    rhs = problem.valence_capped if params.cap_valence else problem.valence_rhs
    a = problem.valence.tocsr()
    for i in range(a.shape[0]):
        lo, hi = a.indptr[i], a.indptr[i + 1]
        prob += (pulp.lpSum(float(m) * x[j] for j, m in zip(a.indices[lo:hi], a.data[lo:hi])) >= float(rhs[i]),
                 f"valence_{int(problem.keypoints[i])}")
    c = problem.cover.tocsr()
    for i in range(c.shape[0]):
        prob += pulp.lpSum(x[j] for j in c.indices[c.indptr[i]:c.indptr[i + 1]]) >= 1, f"cover_{i}"
    if problem.ends is not None and problem.ends.shape[0] and problem.excess_penalty > 0:
        e = problem.ends
        slack = []
        for i in range(e.shape[0]):
            lo, hi = e.indptr[i], e.indptr[i + 1]
            if e.data[lo:hi].sum() <= problem.ends_max[i]:
                continue                                        # cannot be exceeded
            sv = prob.add_variable(f"excess_{int(problem.ends_keypoints[i])}", 0, None, cat=pulp.LpContinuous)
            prob += (pulp.lpSum(float(m) * x[j] for j, m in zip(e.indices[lo:hi], e.data[lo:hi]))
                     <= float(problem.ends_max[i]) + sv, f"ends_{int(problem.ends_keypoints[i])}")
            slack.append(sv)
        if slack:
            prob.setObjective(prob.objective + problem.excess_penalty * pulp.lpSum(slack))
    try:
        with warnings.catch_warnings():
            # pulp 3.3 announces that PULP_CBC_CMD (its bundled CBC) moves to an extra in pulp 4.
            warnings.simplefilter("ignore", DeprecationWarning)
            solver = pulp.PULP_CBC_CMD(msg=False, timeLimit=params.time_limit, threads=params.threads,
                                       gapRel=params.gap_rel)
            prob.solve(solver)
    except pulp.PulpSolverError as e:  # pragma: no cover - depends on the CBC binary
        return None, f"solver_error: {e}", None
    sol = prob.sol_status
    if sol in (pulp.LpSolutionOptimal, pulp.LpSolutionIntegerFeasible):
        vals = np.array([v.varValue if v.varValue is not None else 0.0 for v in x])
        chosen = vals > 0.5
        status = "optimal" if sol == pulp.LpSolutionOptimal else "feasible"
        return chosen, status, float(problem.cost[chosen].sum()) + problem.penalty(chosen)
    if sol == pulp.LpSolutionInfeasible or prob.status == pulp.LpStatusInfeasible:
        return None, "infeasible", None
    return None, "no_solution", None


def independent_blocks(problem: SelectionProblem) -> list[np.ndarray]:
    """Path indices of each independent block of the program, blocks in order of their first path.

    Two paths are in one block when a valence, coverage or curve-end row links them (directly or
    through other paths); no row and no objective term spans two blocks, so each is a program of its own.
    """
    from scipy.sparse.csgraph import connected_components

    rows = [problem.valence, problem.cover] + ([problem.ends] if problem.ends is not None else [])
    incidence = sp.vstack([sp.csr_matrix(m, dtype=np.float64) for m in rows]).tocsr()
    incidence.data[:] = 1.0
    nblock, label = connected_components(incidence.T @ incidence, directed=False)
    order = np.argsort(label, kind="stable")
    return np.split(order, np.cumsum(np.bincount(label, minlength=nblock))[:-1])


def block_problem(problem: SelectionProblem, cols: np.ndarray) -> SelectionProblem:
    """The program restricted to the paths ``cols`` of one block (its rows keep their order)."""
    def part(m: sp.csr_matrix) -> tuple[sp.csr_matrix, np.ndarray]:
        sub = m.tocsr()[:, cols]
        keep = np.flatnonzero(np.diff(sub.indptr) > 0)
        return sub[keep], keep

    val, vk = part(problem.valence)
    cov, ck = part(problem.cover)
    out = SelectionProblem(cost=problem.cost[cols], valence=val, valence_rhs=problem.valence_rhs[vk],
                           valence_capped=problem.valence_capped[vk], keypoints=problem.keypoints[vk],
                           cover=cov, cover_pixels=problem.cover_pixels[ck], excess_penalty=problem.excess_penalty)
    if problem.ends is not None:
        out.ends, ek = part(problem.ends)
        out.ends_max, out.ends_keypoints = problem.ends_max[ek], problem.ends_keypoints[ek]
    return out


#: Paths of one CBC program at most: independent blocks are packed, in order, into programs of up to this
#: many paths (one drawing's few hundred are one program, as before; each CBC call costs ~15 ms to start,
#: and a 4×4 page's 4,700 paths were still solved in time, its 6×6 page's 10,500 were not).
PROGRAM_PATHS = 2048


def _programs(blocks: list[np.ndarray]) -> list[np.ndarray]:
    """Consecutive blocks packed into programs of at most :data:`PROGRAM_PATHS` paths (a bigger block alone)."""
    programs: list[list[np.ndarray]] = [[]]
    size = 0
    for cols in blocks:
        if size and size + len(cols) > PROGRAM_PATHS:
            programs.append([])
            size = 0
        programs[-1].append(cols)
        size += len(cols)
    return [np.sort(np.concatenate(p)) for p in programs]


def select_paths(problem: SelectionProblem, params: SelectConfig) -> tuple[np.ndarray, str, float]:
    """MIP with the documented fallback, block by block; returns ``(chosen, status, objective)``.

    ``status`` is ``optimal`` when every block is, else the status of the first block that is not.
    """
    if len(problem.cost) == 0:
        return np.zeros(0, bool), "empty", 0.0
    programs = _programs(independent_blocks(problem))
    if len(programs) == 1:      # one drawing: the very program of before, rows and all
        return _select_block(problem, params)
    chosen = np.zeros(len(problem.cost), bool)
    status = "optimal"
    for cols in programs:
        part, part_status, _ = _select_block(block_problem(problem, cols), params)
        chosen[cols] = part
        if status == "optimal":
            status = part_status
    # the whole sum, not the blocks' partial sums: the same float as one program's objective
    return chosen, status, float(problem.cost[chosen].sum()) + problem.penalty(chosen)


def _select_block(problem: SelectionProblem, params: SelectConfig) -> tuple[np.ndarray, str, float]:
    """MIP with the documented fallback on one independent block."""
    chosen, status, objective = solve_mip(problem, params)
    if chosen is not None and not satisfies(problem, chosen, capped=params.cap_valence):
        chosen, status = None, f"{status} answer violates a constraint"
    if chosen is None:
        chosen = greedy_selection(problem)
        status = f"fallback: {status}"
        objective = float(problem.cost[chosen].sum()) + problem.penalty(chosen)
    return chosen, status, float(objective)


def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: choose the final paths among the flowed candidates.

    Parameters
    ----------
    cfg : dict
        The ``select`` config section.
    prep, topology, flow : Artifact
        ``topology`` supplies ``paths``, ``key_vertices`` and ``coverage``; ``flow`` the ``energies``.

    Returns
    -------
    Artifact
        data ``chosen`` (path ids), ``status``, ``objective``, ``counts`` (variables, constraints).
    """
    params = from_section(SelectConfig, cfg, "select")
    for name in ("topology", "flow"):
        if name not in inputs:
            raise InputError(f"select stage needs the '{name}' artifact")
    topo, fl = inputs["topology"], inputs["flow"]
    paths = topo.data.get("paths", [])
    energies = np.asarray(fl.data.get("energies", []), np.float64)
    if len(energies) != len(paths):
        raise InputError(f"select: {len(paths)} topology paths but {len(energies)} flow energies")
    if not np.all(np.isfinite(energies)):
        raise InputError("select: flow energies must be finite")
    if paths:
        coverage = unpack_ragged(np.asarray(topo["coverage"]), np.asarray(topo["coverage_offsets"]))
        if len(coverage) != len(paths):
            raise InputError(f"select: {len(paths)} paths but {len(coverage)} coverage lists")
    else:
        coverage = []
    types: dict[int, int] = {}
    branches: dict[int, int] = {}
    kvs = topo.data.get("key_vertices", [])
    for kv in kvs:
        if int(kv.get("keypoint", -1)) >= 0:
            types[int(kv["keypoint"])] = int(kv["type"])
    for b in topo.data.get("keypoint_branches", []):
        branches[int(b["keypoint"])] = int(b["branches"])
    for p in paths:  # keypoints known only through the paths' end types
        for k, t in zip(p.get("end_keypoints", []), p.get("end_types", [])):
            if int(k) >= 0:
                types.setdefault(int(k), int(t))
    problem = build_problem(paths, coverage, energies + params.curve_cost, types, params, branches)
    chosen, status, objective = select_paths(problem, params)
    ids = [int(p["id"]) for p, c in zip(paths, chosen) if c]
    notes = []
    if status not in ("optimal", "empty"):
        # The guard is CBC's time limit: past it the best integer solution found, else the greedy
        # fallback, is used; either way the selection is not proven optimal.
        notes.append(f"selection not proven optimal ({status}; CBC stops at select.time_limit = {params.time_limit:g} s)")
    return Artifact(notes=notes, data={
        "chosen": ids, "status": status, "objective": objective if math.isfinite(objective) else None,
        "counts": {"candidates": len(paths), "chosen": len(ids), "valence_constraints": int(problem.valence.shape[0]),
                   "coverage_constraints": int(problem.cover.shape[0]),
                   "covered_pixels": int(problem.cover_pixels.sum())}})
