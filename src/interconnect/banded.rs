//! The default step-1 solver, `banded` (docs/theory.md §2): the link equations ordered
//! `[a(1); b(1); a(2); …]` form a banded system with `kl = s − 1 + n⁺` sub- and
//! `ku = s − 1 + n⁻` super-diagonals (`s = n⁺ + n⁻`), factorised by [`BandLu`] in `O(N s³)`
//! once per change of `G` and solved in `O(N s²)` per time step. It needs no block of `G`
//! to be invertible and is as well conditioned as the problem.
//!
//! Long chains (at least [`SPLIT_MIN_LINKS`] links) solve it in two halves side by side
//! ([`SplitBandLu`]), so that step 1 scales with the threads like step 2; the split depends
//! only on the chain, never on the thread count, so neither do the results. A split whose
//! halves are ill-conditioned is not used (the whole system is solved at once).

use crate::error::{Error, Result};
use crate::linalg::band_lu::{BandLu, SplitBandLu};
use crate::model::Model;

/// Largest 1-norm condition estimate of a well-posed interconnection system (docs/theory.md §2).
pub const MAX_CONDITION: f64 = 1e15;

/// Chains with at least this many links solve step 1 in two halves in parallel.
pub const SPLIT_MIN_LINKS: usize = 4096;
/// Largest condition estimate of a half, or of the reduced system at the seam, for which the
/// split solve is used.
const SPLIT_MAX_CONDITION: f64 = 1e8;

/// The factorised interconnection system at some time, reused while `G` does not change.
#[derive(Debug, Clone)]
pub struct ChainSolver {
    plus: usize,
    minus: usize,
    subsystems: usize,
    lu: BandLu,
    /// The same system split in two halves, on long chains.
    split: Option<Box<SplitBandLu>>,
    /// Every subsystem's `G` (column-major, concatenated) that `lu` was built from.
    g_built: Vec<f64>,
    /// The window the factors were last checked against.
    window: usize,
    condition: f64,
}

impl ChainSolver {
    /// Assembles and factorises the system at time `t`. Fails when it is not well posed.
    pub fn new(model: &Model, t: usize) -> Result<Self> {
        let d = model.dims;
        let s = d.s();
        let links = model.subsystems - 1;
        let mut solver = Self {
            plus: d.plus,
            minus: d.minus,
            subsystems: model.subsystems,
            lu: BandLu::zeros(0, 0, 0),
            split: None,
            g_built: Vec::new(),
            window: model.window_index(t),
            condition: 1.0,
        };
        let g_now = solver.collect_g(model, t);
        solver.assemble(model, t, links * s, g_now)?;
        Ok(solver)
    }

    fn collect_g(&self, model: &Model, t: usize) -> Vec<f64> {
        let w = model.window(t);
        w.ids
            .iter()
            .flat_map(|&id| model.param_set(id).G.as_slice().iter().copied())
            .collect()
    }

    /// Makes the factors valid for time `t`: refactorises only when some `G` changed.
    pub fn prepare(&mut self, model: &Model, t: usize) -> Result<()> {
        let window = model.window_index(t);
        if window == self.window {
            return Ok(());
        }
        self.window = window;
        let g_now = self.collect_g(model, t);
        if g_now != self.g_built {
            let order = self.lu.n();
            self.assemble(model, t, order, g_now)?;
        }
        Ok(())
    }

    fn assemble(&mut self, model: &Model, t: usize, order: usize, g_now: Vec<f64>) -> Result<()> {
        let (p, m) = (self.plus, self.minus);
        let s = p + m;
        if order == 0 {
            self.g_built = g_now;
            self.condition = 1.0;
            return Ok(());
        }
        let mut lu = BandLu::zeros(order, s - 1 + p, s - 1 + m);
        let links = self.subsystems - 1;
        for i in 1..=links {
            let base = (i - 1) * s;
            let g_i = &model.params(t, i).G;
            let g_next = &model.params(t, i + 1).G;
            // Rows of a(i): a(i) − G11(i) a(i−1) − G12(i) b(i).
            for r in 0..p {
                lu.set(base + r, base + r, 1.0);
                if i > 1 {
                    for c in 0..p {
                        lu.set(base + r, base - s + c, -g_i[(r, c)]);
                    }
                }
                for c in 0..m {
                    lu.set(base + r, base + p + c, -g_i[(r, p + c)]);
                }
            }
            // Rows of b(i): b(i) − G21(i+1) a(i) − G22(i+1) b(i+1).
            for r in 0..m {
                for c in 0..p {
                    lu.set(base + p + r, base + c, -g_next[(p + r, c)]);
                }
                lu.set(base + p + r, base + p + r, 1.0);
                if i < links {
                    for c in 0..m {
                        lu.set(base + p + r, base + s + p + c, -g_next[(p + r, p + c)]);
                    }
                }
            }
        }
        let split = if links >= SPLIT_MIN_LINKS {
            SplitBandLu::new(&lu, links / 2 * s, SPLIT_MAX_CONDITION).map(Box::new)
        } else {
            None
        };
        lu.factor();
        if let Some(col) = lu.zero_pivot() {
            let link = col / s + 1;
            return Err(Error::IllPosed {
                file: model.name.clone(),
                t,
                msg: format!(
                    "the equations are singular (zero pivot at the link between subsystems {link} and {}); check model.G",
                    link + 1
                ),
            });
        }
        let condition = lu.condition_estimate();
        if condition > MAX_CONDITION || !condition.is_finite() {
            return Err(Error::IllPosed {
                file: model.name.clone(),
                t,
                msg: format!(
                    "condition estimate {condition:.3e} exceeds {MAX_CONDITION:e}; check model.G"
                ),
            });
        }
        self.lu = lu;
        self.split = split;
        self.g_built = g_now;
        self.condition = condition;
        Ok(())
    }

    /// 1-norm condition estimate of the current factors (1 for a chain without links).
    pub fn condition(&self) -> f64 {
        self.condition
    }

    /// Solves (P2)–(P4): given `z` (`N · s` values, `z(i) = [z⁺(i); z⁻(i)]` for each `i`),
    /// writes `v` (`N · s` values, `v(i) = [v⁺(i); v⁻(i)]`). `rhs` is scratch of any length
    /// (resized once; no allocation afterwards).
    pub fn solve(&self, z: &[f64], v: &mut [f64], rhs: &mut Vec<f64>) {
        let (p, m) = (self.plus, self.minus);
        let s = p + m;
        let links = self.subsystems - 1;
        if links == 0 || s == 0 {
            v.fill(0.0);
            return;
        }
        if let Some(halves) = self.halves() {
            let b = halves.boundary();
            let (head, rest) = z.split_at(b * s);
            let (shared, tail) = rest.split_at(s);
            let [rhs1, rhs2, seam] = halves.scratch(rhs);
            halves.forward_both(head, shared, tail, rhs1, rhs2);
            halves.seam(rhs1, rhs2, seam);
            let (v1, v2) = v.split_at_mut(b * s + p);
            halves.finish_first(rhs1, seam, v1);
            halves.finish_second(rhs2, seam, v2);
            return;
        }
        let order = links * s;
        rhs.resize(order, 0.0);
        with_link_sizes(p, m, |p, s| {
            fill_links(p, s, z, rhs);
            self.lu.solve(rhs);
            // v⁺(1) = 0 and v⁻(N) = 0 (P4).
            v[..p].fill(0.0);
            v[order + p..].fill(0.0);
            take_links(p, s, rhs, &mut v[p..order + p]);
        });
    }

    /// The split solve in its parts, on chains long enough to have one (docs/theory.md §2):
    /// for a caller that runs each half's own work on the thread that solves it.
    pub fn halves(&self) -> Option<ChainHalves<'_>> {
        self.split.as_deref().map(|split| ChainHalves {
            solver: self,
            split,
        })
    }
}

/// [`ChainSolver::solve`] split at a link: the first half's links read `z` of subsystems
/// `0..=b` and write `v` up to `v⁺(b)`, the second's read `z` from subsystem `b` on and write
/// `v` from `v⁻(b)` on (`b` = [`ChainHalves::boundary`], 0-based). Subsystem `b` is the only
/// one both halves touch: its `z` must be known before either half starts, and its `v` is
/// whole only when both have finished. The result is [`ChainSolver::solve`]'s, bit for bit.
pub struct ChainHalves<'a> {
    solver: &'a ChainSolver,
    split: &'a SplitBandLu,
}

impl ChainHalves<'_> {
    /// The subsystem both halves touch (0-based): the first half holds links `0..b`.
    pub fn boundary(&self) -> usize {
        self.split.first_rows() / (self.solver.plus + self.solver.minus)
    }

    /// `scratch` (resized once) as the halves' right-hand sides and the seam's.
    pub fn scratch<'s>(&self, scratch: &'s mut Vec<f64>) -> [&'s mut [f64]; 3] {
        let s = self.solver.plus + self.solver.minus;
        let order = (self.solver.subsystems - 1) * s;
        let seam_len = 3 * s; // kl + ku = 3s − 2
        scratch.resize(order + seam_len, 0.0);
        let (rhs, seam) = scratch.split_at_mut(order);
        let (rhs1, rhs2) = rhs.split_at_mut(self.split.first_rows());
        [rhs1, rhs2, seam]
    }

    /// The first half's right-hand side from `z` of subsystems `0..b` (`head`) and of `b`
    /// (`shared`), and its block solved.
    pub fn forward_first(&self, head: &[f64], shared: &[f64], rhs: &mut [f64]) {
        self.fill_first(head, shared, rhs);
        self.split.solve_block(false, rhs);
    }

    /// The second half's right-hand side from `z` of subsystem `b` (`shared`) and of those
    /// after it (`tail`), and its block solved.
    pub fn forward_second(&self, shared: &[f64], tail: &[f64], rhs: &mut [f64]) {
        self.fill_second(shared, tail, rhs);
        self.split.solve_block(true, rhs);
    }

    /// [`ChainHalves::forward_first`] and [`ChainHalves::forward_second`] on this thread,
    /// the two blocks' sweeps side by side ([`SplitBandLu::solve_blocks`]): the same bits.
    pub fn forward_both(
        &self,
        head: &[f64],
        shared: &[f64],
        tail: &[f64],
        rhs1: &mut [f64],
        rhs2: &mut [f64],
    ) {
        self.fill_first(head, shared, rhs1);
        self.fill_second(shared, tail, rhs2);
        self.split.solve_blocks(rhs1, rhs2);
    }

    fn fill_first(&self, head: &[f64], shared: &[f64], rhs: &mut [f64]) {
        with_link_sizes(self.solver.plus, self.solver.minus, |p, s| {
            let (before, last) = rhs.split_at_mut(rhs.len() - s);
            fill_links(p, s, head, before);
            fill_link(p, s, &head[head.len() - s..], shared, last);
        });
    }

    fn fill_second(&self, shared: &[f64], tail: &[f64], rhs: &mut [f64]) {
        with_link_sizes(self.solver.plus, self.solver.minus, |p, s| {
            let (first, after) = rhs.split_at_mut(s);
            fill_link(p, s, shared, &tail[..s], first);
            fill_links(p, s, tail, after);
        });
    }

    /// The reduced system at the seam, once both halves are forward-solved.
    pub fn seam(&self, rhs1: &[f64], rhs2: &[f64], seam: &mut [f64]) {
        self.split.solve_seam(rhs1, rhs2, seam);
    }

    /// The first half's `v`: `out` is `v` of subsystems `0..b` and `v⁺(b)`.
    pub fn finish_first(&self, rhs: &mut [f64], seam: &[f64], out: &mut [f64]) {
        self.split.finish_block(false, rhs, seam);
        let p = self.solver.plus;
        out[..p].fill(0.0); // v⁺(1) = 0 (P4)
        with_link_sizes(p, self.solver.minus, |p, s| {
            take_links(p, s, rhs, &mut out[p..])
        });
    }

    /// The second half's `v`: `out` is `v⁻(b)` and `v` of the subsystems after `b`.
    pub fn finish_second(&self, rhs: &mut [f64], seam: &[f64], out: &mut [f64]) {
        self.split.finish_block(true, rhs, seam);
        let len = rhs.len();
        out[len..].fill(0.0); // v⁻(N) = 0 (P4)
        with_link_sizes(self.solver.plus, self.solver.minus, |p, s| {
            take_links(p, s, rhs, &mut out[..len])
        });
    }
}

/// Calls `f(p, s)` with `p = n⁺` and `s = n⁺ + n⁻` as constants for the chains with
/// `n⁺, n⁻ ≤ 2`, so that the loops over a link's values in `f` unroll.
#[inline(always)]
fn with_link_sizes<R>(p: usize, m: usize, f: impl FnOnce(usize, usize) -> R) -> R {
    match (p, m) {
        (1, 1) => f(1, 2),
        (1, 0) => f(1, 1),
        (0, 1) => f(0, 1),
        (2, 2) => f(2, 4),
        (2, 1) => f(2, 3),
        (1, 2) => f(1, 3),
        (2, 0) => f(2, 2),
        (0, 2) => f(0, 2),
        _ => f(p, p + m),
    }
}

/// The right-hand side of the links between consecutive subsystems of `z` (one row of `rhs`
/// per link `j`): `[a(j); b(j)] = [z⁺(j); z⁻(j+1)]` (`p` and `s − p` values).
#[inline(always)]
fn fill_links(p: usize, s: usize, z: &[f64], rhs: &mut [f64]) {
    let pairs = z.windows(2 * s).step_by(s);
    for (row, zz) in rhs.chunks_exact_mut(s).zip(pairs) {
        fill_link(p, s, &zz[..s], &zz[s..], row);
    }
}

/// One link's right-hand side, `[z⁺(j); z⁻(j+1)]`, from `z(j)` (`left`) and `z(j+1)`
/// (`right`).
// Blocks of one or two numbers: loops beat memcpy calls.
#[allow(clippy::manual_memcpy)]
#[inline(always)]
fn fill_link(p: usize, s: usize, left: &[f64], right: &[f64], row: &mut [f64]) {
    for k in 0..p {
        row[k] = left[k];
    }
    for k in p..s {
        row[k] = right[k];
    }
}

/// The links' solution `[v⁺(j+1); v⁻(j)]` from `rhs` into `out`, which starts at
/// `v⁻(j)` of the first link: `v(i) = [v⁺(i); v⁻(i)]` per subsystem.
#[allow(clippy::manual_memcpy)]
#[inline(always)]
fn take_links(p: usize, s: usize, rhs: &[f64], out: &mut [f64]) {
    let m = s - p;
    for (row, o) in rhs.chunks_exact(s).zip(out.chunks_exact_mut(s)) {
        for k in p..s {
            o[k - p] = row[k];
        }
        for k in 0..p {
            o[m + k] = row[k];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::random_model;
    use super::*;
    use crate::config::ConfigSource;
    use nalgebra::{DMatrix, DVector};

    /// Dense reference: unknowns are all `w(i)` and `v(i)`; equations (P2), (P3), (P4) as
    /// written in docs/theory.md §1, without the link elimination used by the solver.
    fn dense_solve(model: &Model, t: usize, z: &[f64]) -> Vec<f64> {
        let d = model.dims;
        let (s, p, n) = (d.s(), d.plus, model.subsystems);
        let size = 2 * n * s; // [w(1..N); v(1..N)]
        let mut a = DMatrix::zeros(size, size);
        let mut b = DVector::zeros(size);
        let w = |i: usize, k: usize| (i - 1) * s + k;
        let v = |i: usize, k: usize| n * s + (i - 1) * s + k;
        let mut row = 0;
        for i in 1..=n {
            let g = &model.params(t, i).G;
            for k in 0..s {
                // w(i) − G v(i) = z(i)
                a[(row, w(i, k))] = 1.0;
                for c in 0..s {
                    a[(row, v(i, c))] -= g[(k, c)];
                }
                b[row] = z[(i - 1) * s + k];
                row += 1;
            }
        }
        for i in 1..=n {
            for k in 0..s {
                a[(row, v(i, k))] = 1.0;
                if k < p && i > 1 {
                    a[(row, w(i - 1, k))] = -1.0; // v⁺(i) = w⁺(i−1)
                } else if k >= p && i < n {
                    a[(row, w(i + 1, k))] = -1.0; // v⁻(i) = w⁻(i+1)
                } // else v⁺(1) = 0 or v⁻(N) = 0
                row += 1;
            }
        }
        let x = a.lu().solve(&b).expect("dense system singular");
        x.as_slice()[n * s..].to_vec()
    }

    #[test]
    fn banded_equals_dense_solve() {
        let mut seed = 0;
        for &n_sub in &[1, 2, 3, 10, 200] {
            // One-way chains too (n⁺ or n⁻ = 0): each pair of sizes copies its links itself.
            for plus in 0..=3 {
                for minus in 0..=3 {
                    if plus + minus == 0 || (n_sub == 200 && plus + minus > 4) {
                        continue; // the dense reference is O((2Ns)³)
                    }
                    seed += 1;
                    let model = random_model(n_sub, plus, minus, seed, n_sub > 1, 0.0);
                    let s = plus + minus;
                    let mut solver = ChainSolver::new(&model, 1).unwrap();
                    let mut rhs = Vec::new();
                    for t in 1..=5 {
                        solver.prepare(&model, t).unwrap();
                        let z: Vec<f64> = (0..n_sub * s)
                            .map(|k| ((k * 7 + t) as f64 * 0.37).sin())
                            .collect();
                        let mut v = vec![f64::NAN; n_sub * s];
                        solver.solve(&z, &mut v, &mut rhs);
                        let exact = dense_solve(&model, t, &z);
                        let scale = exact.iter().fold(1e-300f64, |a, b| a.max(b.abs()));
                        for k in 0..v.len() {
                            assert!(
                                (v[k] - exact[k]).abs() <= 1e-12 * scale,
                                "N={n_sub} plus={plus} minus={minus} t={t} k={k}: {} vs {}",
                                v[k],
                                exact[k]
                            );
                        }
                    }
                }
            }
        }
    }

    /// A chain long enough for the split solve: equal to the unsplit banded solve.
    #[test]
    fn split_solve_equals_whole_solve() {
        let n_sub = SPLIT_MIN_LINKS + 7;
        let model = random_model(n_sub, 1, 2, 77, false, 0.0);
        let solver = ChainSolver::new(&model, 1).unwrap();
        assert!(solver.split.is_some());
        let s = 3;
        let z: Vec<f64> = (0..n_sub * s).map(|k| (k as f64 * 0.37).sin()).collect();
        let (mut v, mut rhs) = (vec![0.0; n_sub * s], Vec::new());
        solver.solve(&z, &mut v, &mut rhs);
        let mut whole = solver.clone();
        whole.split = None;
        let mut v_whole = vec![0.0; n_sub * s];
        whole.solve(&z, &mut v_whole, &mut rhs);
        let scale = v_whole.iter().fold(0.0f64, |a, b| a.max(b.abs()));
        for k in 0..v.len() {
            assert!((v[k] - v_whole[k]).abs() <= 1e-13 * scale, "{k}");
        }
    }

    #[test]
    fn singular_system_is_reported() {
        // G12 = G21 = 1 with G11 = G22 = 0 on N = 2: b(1) = a(1) and a(1) = b(1) + z.
        let text = "subsystems = 2\nsteps = 3\n[interconnection]\nplus = 1\nminus = 1\n\
                    [model]\nA = [[0.5]]\nB = [[0.1, 0.1]]\nD = [[1.0], [1.0]]\n\
                    G = [[0.0, 1.0], [1.0, 0.0]]\nJ = [[1.0]]\nM = [[1.0]]\n\
                    [dropout]\np = 1.0\n[initial]\ncov = [[1.0]]\n";
        let src = ConfigSource::from_text("s.toml", ".".into(), text.into()).unwrap();
        let model = Model::from_config(&src).unwrap();
        let err = ChainSolver::new(&model, 1).unwrap_err().to_string();
        assert!(err.contains("t = 1") && err.contains("singular"), "{err}");
    }
}
