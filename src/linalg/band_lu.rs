//! LU factorisation with partial pivoting of a general banded matrix, LAPACK `gbtrf`/`gbtrs`
//! style, and a 1-norm condition estimate (Hager–Higham, as LAPACK's `gecon`). Pure linear
//! algebra: it knows nothing of chains or filters.
//!
//! Storage: `A(r, c)` with `c − ku ≤ r ≤ c + kl` lives at `ab[c · ld + kv + r − c]`, where
//! `kv = kl + ku` leaves room for the fill-in that row interchanges cause (`U` gets upper
//! bandwidth `kv`) and `ld = 2 kl + ku + 1`.

/// A banded matrix being assembled, then factorised in place by [`BandLu::factor`].
#[derive(Debug, Clone)]
pub struct BandLu {
    n: usize,
    kl: usize,
    ku: usize,
    ab: Vec<f64>,
    ipiv: Vec<usize>,
    /// `1 / U(j, j)`: the solves multiply instead of divide, which shortens the dependency
    /// chain of the back substitution (a division's latency is several multiplications').
    inv_pivot: Vec<f64>,
    /// `‖A‖₁`, recorded before factorisation.
    norm1: f64,
    /// First column with an exactly zero pivot, if any.
    zero_pivot: Option<usize>,
}

impl BandLu {
    /// A zero `n × n` matrix with `kl` sub- and `ku` super-diagonals.
    pub fn zeros(n: usize, kl: usize, ku: usize) -> Self {
        let ld = 2 * kl + ku + 1;
        Self {
            n,
            kl,
            ku,
            ab: vec![0.0; ld * n],
            ipiv: vec![0; n],
            inv_pivot: vec![0.0; n],
            norm1: 0.0,
            zero_pivot: None,
        }
    }

    /// Order of the matrix.
    pub fn n(&self) -> usize {
        self.n
    }

    fn ld(&self) -> usize {
        2 * self.kl + self.ku + 1
    }

    #[inline]
    fn idx(&self, r: usize, c: usize) -> usize {
        c * self.ld() + self.kl + self.ku + r - c
    }

    /// `A(r, c)` (0-based) before factorisation; 0 outside the band.
    pub fn get(&self, r: usize, c: usize) -> f64 {
        if r > c + self.kl || c > r + self.ku {
            return 0.0;
        }
        self.ab[self.idx(r, c)]
    }

    /// The diagonal block of rows and columns `start..end`, before factorisation.
    pub fn block(&self, start: usize, end: usize) -> BandLu {
        let mut out = BandLu::zeros(end - start, self.kl, self.ku);
        for c in start..end {
            for r in c.saturating_sub(self.ku).max(start)..(c + self.kl + 1).min(end) {
                out.set(r - start, c - start, self.get(r, c));
            }
        }
        out
    }

    /// Sets `A(r, c)` (0-based) before factorisation; `(r, c)` must lie in the band.
    pub fn set(&mut self, r: usize, c: usize, v: f64) {
        assert!(
            r <= c + self.kl && c <= r + self.ku,
            "({r}, {c}) outside the band"
        );
        let k = self.idx(r, c);
        self.ab[k] = v;
    }

    /// Factorises `A = P L U` in place (partial pivoting). A zero pivot does not stop the
    /// factorisation; it is reported by [`BandLu::zero_pivot`].
    pub fn factor(&mut self) {
        let (n, kl, ku) = (self.n, self.kl, self.ku);
        let kv = kl + ku;
        self.norm1 = (0..n)
            .map(|c| {
                (c.saturating_sub(ku)..(c + kl + 1).min(n))
                    .map(|r| self.ab[self.idx(r, c)].abs())
                    .sum::<f64>()
            })
            .fold(0.0, f64::max);
        self.zero_pivot = None;
        let ld = self.ld();
        let mut ju = 0;
        for j in 0..n {
            let km = kl.min(n - 1 - j);
            let col = j * ld + kv;
            let mut jp = 0;
            let mut best = self.ab[col].abs();
            for r in 1..=km {
                if self.ab[col + r].abs() > best {
                    best = self.ab[col + r].abs();
                    jp = r;
                }
            }
            self.ipiv[j] = j + jp;
            if best == 0.0 {
                self.zero_pivot.get_or_insert(j);
                continue;
            }
            ju = ju.max((j + ku + jp).min(n - 1));
            if jp != 0 {
                for c in j..=ju {
                    let (a, b) = (self.idx(j, c), self.idx(j + jp, c));
                    self.ab.swap(a, b);
                }
            }
            let pivot = self.ab[col];
            self.inv_pivot[j] = 1.0 / pivot;
            for r in 1..=km {
                self.ab[col + r] /= pivot;
            }
            for c in j + 1..=ju {
                let a = self.ab[self.idx(j, c)];
                if a != 0.0 {
                    let base = self.idx(j, c);
                    for r in 1..=km {
                        self.ab[base + r] -= self.ab[col + r] * a;
                    }
                }
            }
        }
    }

    /// First column (0-based) whose pivot is exactly zero: the matrix is singular.
    pub fn zero_pivot(&self) -> Option<usize> {
        self.zero_pivot
    }

    /// Solves `A x = b` in place. Requires a factorised matrix without zero pivot.
    pub fn solve(&self, b: &mut [f64]) {
        Self::solve_each([(self, b)]);
    }

    /// Solves each `A_k x = b_k` in place ([`BandLu::solve`] of each, bit for bit). Every
    /// sweep is one chain of dependent multiply-subtracts, bound by their latency, not by
    /// the core's throughput: systems of the same bandwidths are swept side by side, a row of
    /// each in turn, so that one core works on `K` chains at once in about the time of one.
    pub fn solve_each<const K: usize>(systems: [(&BandLu, &mut [f64]); K]) {
        let Some((first, _)) = systems.first() else {
            return;
        };
        let (kl, kv) = (first.kl, first.kl + first.ku);
        let windowed = |lu: &BandLu| lu.kl == kl && lu.kl + lu.ku == kv && lu.n > kv + 1;
        if !systems.iter().all(|(lu, _)| windowed(lu)) {
            // One at a time, each with its own sweeps where it has them.
            for (lu, b) in systems {
                match K {
                    1 => lu.solve_general(b),
                    _ => lu.solve(b),
                }
            }
            return;
        }
        // The bandwidths of the chain systems with n⁺, n⁻ ≤ 2 get sweeps that keep the
        // band of unknowns in registers.
        match (kl, kv) {
            (2, 4) => solve_windowed::<2, 4, K>(systems),
            (1, 1) => solve_windowed::<1, 1, K>(systems),
            (0, 1) => solve_windowed::<0, 1, K>(systems),
            (1, 2) => solve_windowed::<1, 2, K>(systems),
            (4, 7) => solve_windowed::<4, 7, K>(systems),
            (3, 7) => solve_windowed::<3, 7, K>(systems),
            (5, 10) => solve_windowed::<5, 10, K>(systems),
            _ => systems.into_iter().for_each(|(lu, b)| lu.solve_general(b)),
        }
    }

    fn solve_general(&self, b: &mut [f64]) {
        let (n, kl, kv) = (self.n, self.kl, self.kl + self.ku);
        let ld = self.ld();
        for j in 0..n.saturating_sub(1) {
            let l = self.ipiv[j];
            if l != j {
                b.swap(l, j);
            }
            let bj = b[j];
            if bj != 0.0 {
                let (col, k) = (j * ld + kv, kl.min(n - 1 - j));
                let multipliers = &self.ab[col + 1..col + 1 + k];
                for (x, l) in b[j + 1..j + 1 + k].iter_mut().zip(multipliers) {
                    *x -= l * bj;
                }
            }
        }
        for j in (0..n).rev() {
            let col = j * ld + kv;
            b[j] *= self.inv_pivot[j];
            let bj = b[j];
            if bj != 0.0 {
                let first = j.saturating_sub(kv);
                let column = &self.ab[col - (j - first)..col];
                for (x, u) in b[first..j].iter_mut().zip(column) {
                    *x -= u * bj;
                }
            }
        }
    }

    /// Solves `Aᵀ x = b` in place.
    pub fn solve_transpose(&self, b: &mut [f64]) {
        let (n, kl, kv) = (self.n, self.kl, self.kl + self.ku);
        let ld = self.ld();
        for j in 0..n {
            let col = j * ld + kv;
            let mut s = b[j];
            for r in j.saturating_sub(kv)..j {
                s -= self.ab[col + r - j] * b[r];
            }
            b[j] = s * self.inv_pivot[j];
        }
        for j in (0..n.saturating_sub(1)).rev() {
            let col = j * ld + kv;
            let mut s = b[j];
            for r in 1..=kl.min(n - 1 - j) {
                s -= self.ab[col + r] * b[j + r];
            }
            b[j] = s;
            let l = self.ipiv[j];
            if l != j {
                b.swap(l, j);
            }
        }
    }

    /// Estimate of the 1-norm condition number `‖A‖₁ ‖A⁻¹‖₁` (Hager's method with Higham's
    /// extra test vector, as LAPACK's `dlacn2`); a lower bound, usually within a factor 3.
    /// Infinite when a pivot is zero.
    pub fn condition_estimate(&self) -> f64 {
        let n = self.n;
        if n == 0 {
            return 1.0;
        }
        if self.zero_pivot.is_some() {
            return f64::INFINITY;
        }
        let mut x = vec![1.0 / n as f64; n];
        let mut est = 0.0f64;
        let mut last_j = usize::MAX;
        for iter in 0..5 {
            self.solve(&mut x);
            let new_est: f64 = x.iter().map(|v| v.abs()).sum();
            if iter > 0 && new_est <= est {
                est = est.max(new_est);
                break;
            }
            est = new_est;
            let mut z: Vec<f64> = x
                .iter()
                .map(|&v| if v >= 0.0 { 1.0 } else { -1.0 })
                .collect();
            self.solve_transpose(&mut z);
            let (j, zmax) = z
                .iter()
                .enumerate()
                .map(|(k, v)| (k, v.abs()))
                .fold((0, -1.0), |a, b| if b.1 > a.1 { b } else { a });
            if j == last_j || (iter > 0 && zmax <= z[last_j].abs()) {
                break;
            }
            last_j = j;
            x.iter_mut().for_each(|v| *v = 0.0);
            x[j] = 1.0;
        }
        // Higham's alternating test vector guards against Hager's worst cases.
        let mut alt: Vec<f64> = (0..n)
            .map(|k| {
                let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                sign * (1.0 + k as f64 / (n.max(2) - 1) as f64)
            })
            .collect();
        self.solve(&mut alt);
        let alt_est = 2.0 * alt.iter().map(|v| v.abs()).sum::<f64>() / (3.0 * n as f64);
        self.norm1 * est.max(alt_est)
    }
}

/// [`BandLu::solve_each`] for `kl = KL`, `kl + ku = KV` and every `n > KV + 1`: the rows of
/// each `b` still being eliminated (forward) and its last solved unknowns (backward, as dot
/// products) are held in local arrays, so that no value makes a round trip through memory
/// on the dependency chain of a sweep. Row `j` of every system is swept before row `j + 1`
/// of any (backward: counted from each system's end).
fn solve_windowed<const KL: usize, const KV: usize, const K: usize>(
    systems: [(&BandLu, &mut [f64]); K],
) {
    let rows = systems.iter().map(|(lu, _)| lu.n).max().unwrap_or(0);
    let mut forward = systems.map(|(lu, b)| Forward::<KL, KV>::new(lu, b));
    for j in 0..rows {
        for sweep in &mut forward {
            if j < sweep.n {
                sweep.row(j);
            }
        }
    }
    let mut backward = forward.map(Forward::backward);
    for i in 0..rows {
        for sweep in &mut backward {
            if i < sweep.n {
                sweep.row(sweep.n - 1 - i);
            }
        }
    }
}

/// The leading dimension of the storage, `2 kl + ku + 1`, for `kl = KL`, `kl + ku = KV`.
const fn ld<const KL: usize, const KV: usize>() -> usize {
    KL + KV + 1
}

/// The forward sweep `L y = P b` of one system: `cur` is `b[j]`, `pending[r]` is
/// `b[j + 1 + r]`; multipliers of rows past the end are zero (never set). The factors'
/// slices are held here, not behind the `BandLu`, so that a store to `b` does not make the
/// loop read them again.
struct Forward<'a, const KL: usize, const KV: usize> {
    n: usize,
    ab: &'a [f64],
    ipiv: &'a [usize],
    inv_pivot: &'a [f64],
    b: &'a mut [f64],
    cur: f64,
    pending: [f64; KL],
}

impl<'a, const KL: usize, const KV: usize> Forward<'a, KL, KV> {
    fn new(lu: &'a BandLu, b: &'a mut [f64]) -> Self {
        let n = lu.n;
        let cur = b[0];
        let pending = std::array::from_fn(|r| if 1 + r < n { b[1 + r] } else { 0.0 });
        Self {
            n,
            ab: &lu.ab,
            ipiv: &lu.ipiv,
            inv_pivot: &lu.inv_pivot,
            b,
            cur,
            pending,
        }
    }

    #[inline(always)]
    fn row(&mut self, j: usize) {
        let (n, b, pending) = (self.n, &mut *self.b, &mut self.pending);
        let l = self.ipiv[j];
        if l != j {
            // Rare: swap through memory.
            b[j] = self.cur;
            for (r, &p) in pending.iter().enumerate() {
                if j + 1 + r < n {
                    b[j + 1 + r] = p;
                }
            }
            b.swap(l, j);
            self.cur = b[j];
            for (r, p) in pending.iter_mut().enumerate() {
                *p = if j + 1 + r < n { b[j + 1 + r] } else { 0.0 };
            }
        }
        let cur = self.cur;
        b[j] = cur;
        let col = j * ld::<KL, KV>() + KV;
        let multipliers: &[f64; KL] = self.ab[col + 1..col + 1 + KL].try_into().expect("KL");
        for (p, m) in pending.iter_mut().zip(multipliers) {
            *p -= m * cur;
        }
        if KL > 0 {
            // Element by element (not copy_within), so that the array stays in registers.
            self.cur = pending[0];
            for r in 1..KL {
                pending[r - 1] = pending[r];
            }
            pending[KL - 1] = if j + 1 + KL < n { b[j + 1 + KL] } else { 0.0 };
        } else if j + 1 < n {
            self.cur = b[j + 1];
        }
    }

    /// The backward sweep of the same system, once this one has passed every row.
    fn backward(self) -> Backward<'a, KL, KV> {
        Backward {
            n: self.n,
            ab: self.ab,
            inv_pivot: self.inv_pivot,
            b: self.b,
            solved: [0.0; KV],
        }
    }
}

/// The backward sweep `U x = y` of one system, `x[j] = (y[j] − Σ U(j, j+r) x[j+r]) /
/// U(j, j)`: `solved[r]` is `x[j + 1 + r]`; `U(j, j+r)` lives at `ab[(j+r)·ld + kv − r]`.
struct Backward<'a, const KL: usize, const KV: usize> {
    n: usize,
    ab: &'a [f64],
    inv_pivot: &'a [f64],
    b: &'a mut [f64],
    solved: [f64; KV],
}

impl<const KL: usize, const KV: usize> Backward<'_, KL, KV> {
    #[inline(always)]
    fn row(&mut self, j: usize) {
        let (n, ld, ab, solved) = (self.n, ld::<KL, KV>(), self.ab, &mut self.solved);
        let mut acc = self.b[j];
        if j + KV < n {
            // U(j, j+r) for r = 1..=KV, every (ld − 1)-th value from U(j, j+1) on: one
            // bounds check for the row.
            let first = (j + 1) * ld + KV - 1;
            let u = &ab[first..=first + (KV - 1) * (ld - 1)];
            for r in (1..=KV).rev() {
                acc -= u[(r - 1) * (ld - 1)] * solved[r - 1];
            }
        } else {
            for r in (1..=KV).rev() {
                if j + r < n {
                    acc -= ab[(j + r) * ld + KV - r] * solved[r - 1];
                }
            }
        }
        let x = acc * self.inv_pivot[j];
        self.b[j] = x;
        for r in (1..KV).rev() {
            solved[r] = solved[r - 1];
        }
        solved[0] = x;
    }
}

/// A banded system solved as two diagonal blocks side by side (the SPIKE partition of Sameh
/// and Polizzi). With `A = [[A₁, E₁], [F₂, A₂]]` split after row `m₁`, `E₁` couples the last
/// `ku` rows of the first block to the first `ku` unknowns of the second and `F₂` the first
/// `kl` rows of the second block to the last `kl` unknowns of the first. With the spikes
/// `V = A₁⁻¹ E₁`, `W = A₂⁻¹ F₂` (computed once) and `g_k = A_k⁻¹ b_k` (the two solves run in
/// parallel, or side by side on one thread: [`SplitBandLu::solve_blocks`]),
/// `x₁ = g₁ − V x₂[..ku]` and `x₂ = g₂ − W x₁[m₁−kl..]`, whose rows at the seam form a reduced
/// system of order `kl + ku`:
///
/// ```text
/// [ I              V[m₁−kl.., ..] ] [ x₁[m₁−kl..] ]   [ g₁[m₁−kl..] ]
/// [ W[..ku, ..]    I              ] [ x₂[..ku]    ] = [ g₂[..ku]    ]
/// ```
///
/// It needs both blocks nonsingular, which a nonsingular `A` does not guarantee; the
/// constructor refuses a split whose blocks or reduced system are ill-conditioned.
#[derive(Debug, Clone)]
pub struct SplitBandLu {
    m1: usize,
    kl: usize,
    ku: usize,
    first: BandLu,
    second: BandLu,
    /// `V` (`m₁ × ku`) and `W` (`m₂ × kl`), column-major.
    v: Vec<f64>,
    w: Vec<f64>,
    reduced: BandLu,
}

impl SplitBandLu {
    /// Splits the assembled (not yet factorised) `a` after row `m1`. `None` when a block or
    /// the reduced system has a zero pivot or a condition estimate above `max_condition`.
    pub fn new(a: &BandLu, m1: usize, max_condition: f64) -> Option<Self> {
        let (n, kl, ku) = (a.n, a.kl, a.ku);
        if kl + ku == 0 || m1 < kl.max(1) || n - m1 < ku.max(1) {
            return None;
        }
        let well =
            |lu: &BandLu| lu.zero_pivot().is_none() && lu.condition_estimate() <= max_condition;
        let mut first = a.block(0, m1);
        let mut second = a.block(m1, n);
        first.factor();
        second.factor();
        if !well(&first) || !well(&second) {
            return None;
        }
        let m2 = n - m1;
        let mut v = vec![0.0; m1 * ku];
        for (c, col) in v.chunks_exact_mut(m1).enumerate() {
            for r in m1.saturating_sub(ku)..m1 {
                col[r] = a.get(r, m1 + c);
            }
            first.solve(col);
        }
        let mut w = vec![0.0; m2 * kl];
        for (c, col) in w.chunks_exact_mut(m2).enumerate() {
            for r in 0..kl.min(m2) {
                col[r] = a.get(m1 + r, m1 - kl + c);
            }
            second.solve(col);
        }
        let k = kl + ku;
        let mut reduced = BandLu::zeros(k, k - 1, k - 1);
        for r in 0..kl {
            reduced.set(r, r, 1.0);
            for c in 0..ku {
                reduced.set(r, kl + c, v[c * m1 + m1 - kl + r]);
            }
        }
        for r in 0..ku {
            for c in 0..kl {
                reduced.set(kl + r, c, w[c * m2 + r]);
            }
            reduced.set(kl + r, kl + r, 1.0);
        }
        reduced.factor();
        if !well(&reduced) {
            return None;
        }
        Some(Self {
            m1,
            kl,
            ku,
            first,
            second,
            v,
            w,
            reduced,
        })
    }

    /// Order of the matrix.
    pub fn n(&self) -> usize {
        self.m1 + self.second.n
    }

    /// Order of the first block.
    pub fn first_rows(&self) -> usize {
        self.m1
    }

    /// Solves `A x = b` in place, the two blocks in parallel (rayon); `seam` is scratch of
    /// `kl + ku` values. The result does not depend on the thread count.
    pub fn solve(&self, b: &mut [f64], seam: &mut [f64]) {
        let (b1, b2) = b.split_at_mut(self.m1);
        rayon::join(
            || self.solve_block(false, b1),
            || self.solve_block(true, b2),
        );
        self.solve_seam(b1, b2, seam);
        rayon::join(
            || self.finish_block(false, b1, seam),
            || self.finish_block(true, b2, seam),
        );
    }

    /// The solve in its three parts, for callers that fill and read each block on the
    /// thread that solves it: `g_k = A_k⁻¹ b_k` in place, of the first block (`second` false,
    /// `b` its `m₁` rows) or of the second.
    pub fn solve_block(&self, second: bool, b: &mut [f64]) {
        match second {
            false => self.first.solve(b),
            true => self.second.solve(b),
        }
    }

    /// [`SplitBandLu::solve_block`] of both blocks on this thread, their sweeps side by
    /// side ([`BandLu::solve_each`]): the same bits, in about the time of one block.
    pub fn solve_blocks(&self, b1: &mut [f64], b2: &mut [f64]) {
        BandLu::solve_each([(&self.first, b1), (&self.second, b2)]);
    }

    /// The reduced system at the seam from both blocks' `g_k`: `seam` (at least `kl + ku`
    /// values) receives `[x₁[m₁−kl..]; x₂[..ku]]`.
    pub fn solve_seam(&self, g1: &[f64], g2: &[f64], seam: &mut [f64]) {
        let (kl, ku) = (self.kl, self.ku);
        seam[..kl].copy_from_slice(&g1[self.m1 - kl..]);
        seam[kl..kl + ku].copy_from_slice(&g2[..ku]);
        self.reduced.solve(&mut seam[..kl + ku]);
    }

    /// A block's solution from its `g_k` and the seam's: `x₁ = g₁ − V x₂[..ku]`, `x₂ = g₂ − W
    /// x₁[m₁−kl..]`.
    pub fn finish_block(&self, second: bool, g: &mut [f64], seam: &[f64]) {
        let (x1_end, x2_start) = seam[..self.kl + self.ku].split_at(self.kl);
        match second {
            false => subtract_spikes(g, &self.v, x2_start),
            true => subtract_spikes(g, &self.w, x1_end),
        }
    }
}

/// `x −= S c` for the column-major spikes `S` (`x.len() × c.len()`).
fn subtract_spikes(x: &mut [f64], spikes: &[f64], c: &[f64]) {
    for (col, &a) in spikes.chunks_exact(x.len()).zip(c) {
        if a != 0.0 {
            for (xi, s) in x.iter_mut().zip(col) {
                *xi -= s * a;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use rand::{RngExt, SeedableRng};

    fn random_band(n: usize, kl: usize, ku: usize, seed: u64) -> (BandLu, DMatrix<f64>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut lu = BandLu::zeros(n, kl, ku);
        let mut dense = DMatrix::zeros(n, n);
        for r in 0..n {
            for c in r.saturating_sub(kl)..(r + ku + 1).min(n) {
                // Small diagonal forces pivoting.
                let v: f64 = rng.random_range(-1.0..1.0) * if r == c { 0.01 } else { 1.0 };
                lu.set(r, c, v);
                dense[(r, c)] = v;
            }
        }
        (lu, dense)
    }

    #[test]
    fn solves_match_dense_lu() {
        // Includes every bandwidth with a windowed solve, on long and on short matrices.
        for (n, kl, ku) in [
            (1, 0, 0),
            (5, 1, 2),
            (30, 3, 1),
            (40, 4, 4),
            (7, 6, 6),
            (50, 2, 2),
            (4, 2, 2),
            (6, 2, 2),
            (20, 1, 0),
            (20, 0, 1),
            (20, 1, 1),
            (30, 4, 3),
            (30, 3, 4),
            (40, 5, 5),
        ] {
            let (mut lu, dense) = random_band(n, kl, ku, n as u64);
            lu.factor();
            assert!(lu.zero_pivot().is_none());
            let b = DVector::from_fn(n, |i, _| (i as f64 + 1.0).sin());
            let exact = dense.clone().lu().solve(&b).unwrap();
            let mut x = b.as_slice().to_vec();
            lu.solve(&mut x);
            let exact_t = dense.transpose().lu().solve(&b).unwrap();
            let mut xt = b.as_slice().to_vec();
            lu.solve_transpose(&mut xt);
            for k in 0..n {
                assert!((x[k] - exact[k]).abs() <= 1e-9 * exact.amax().max(1.0));
                assert!((xt[k] - exact_t[k]).abs() <= 1e-9 * exact_t.amax().max(1.0));
            }
        }
    }

    /// Two systems swept side by side: each against a dense LU solve, and bit for bit what
    /// its own solve gives; lengths that differ, pivoting, bandwidths with and without a
    /// windowed sweep, systems too short for one, and bandwidths that differ.
    #[test]
    fn side_by_side_solves_match_dense_lu_and_one_at_a_time() {
        for [(n1, kl1, ku1), (n2, kl2, ku2)] in [
            [(50, 2, 2), (31, 2, 2)],
            [(6, 2, 2), (40, 2, 2)],
            [(41, 1, 1), (41, 1, 1)],
            [(30, 4, 3), (45, 4, 3)],
            [(33, 3, 2), (20, 3, 2)],
            [(4, 2, 2), (3, 2, 2)],
            [(30, 2, 2), (30, 1, 2)],
        ] {
            let (mut a, dense_a) = random_band(n1, kl1, ku1, 11 + n1 as u64);
            let (mut b, dense_b) = random_band(n2, kl2, ku2, 12 + n2 as u64);
            a.factor();
            b.factor();
            let rhs = |n: usize| DVector::from_fn(n, |i, _| (0.3 * i as f64 + 0.5).cos());
            let (rhs_a, rhs_b) = (rhs(n1), rhs(n2));
            let (mut xa, mut xb) = (rhs_a.as_slice().to_vec(), rhs_b.as_slice().to_vec());
            BandLu::solve_each([(&a, xa.as_mut_slice()), (&b, xb.as_mut_slice())]);
            for (lu, dense, rhs, x) in [(&a, dense_a, rhs_a, xa), (&b, dense_b, rhs_b, xb)] {
                let exact = dense.lu().solve(&rhs).unwrap();
                let mut alone = rhs.as_slice().to_vec();
                lu.solve(&mut alone);
                for k in 0..x.len() {
                    assert!((x[k] - exact[k]).abs() <= 1e-9 * exact.amax().max(1.0));
                    assert_eq!(x[k].to_bits(), alone[k].to_bits(), "{n1} {n2} {k}");
                }
            }
        }
    }

    /// The split solve against a dense LU solve, for several band shapes and split points,
    /// with one and two threads (the same bits).
    #[test]
    fn split_solves_match_dense_lu() {
        for (n, kl, ku, m1) in [
            (40, 2, 2, 20),
            (41, 3, 1, 7),
            (30, 1, 3, 26),
            (50, 2, 0, 25),
        ] {
            let (mut lu, mut dense) = random_band(n, kl, ku, 3 + n as u64);
            // A dominant diagonal keeps both blocks nonsingular.
            for k in 0..n {
                let v = lu.get(k, k) + 4.0;
                lu.set(k, k, v);
                dense[(k, k)] = v;
            }
            let split = SplitBandLu::new(&lu, m1, 1e12).expect("well-conditioned split");
            assert_eq!(split.n(), n);
            let b = DVector::from_fn(n, |i, _| (i as f64 * 0.7 + 1.0).sin());
            let exact = dense.lu().solve(&b).unwrap();
            let solve = |threads: usize| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let mut x = b.as_slice().to_vec();
                pool.install(|| split.solve(&mut x, &mut [0.0; 8]));
                x
            };
            let (one, two) = (solve(1), solve(2));
            for k in 0..n {
                assert!(
                    (one[k] - exact[k]).abs() <= 1e-13 * exact.amax(),
                    "{n} {kl} {ku}"
                );
                assert_eq!(one[k].to_bits(), two[k].to_bits());
            }
        }
    }

    /// `[[0, 1], [1, 0]]` is nonsingular, but its diagonal blocks are zero.
    #[test]
    fn split_with_singular_block_is_refused() {
        let mut lu = BandLu::zeros(2, 1, 1);
        lu.set(0, 1, 1.0);
        lu.set(1, 0, 1.0);
        assert!(SplitBandLu::new(&lu, 1, 1e12).is_none());
    }

    #[test]
    fn condition_estimate_is_close_to_exact() {
        let (mut lu, dense) = random_band(25, 2, 3, 7);
        lu.factor();
        let inv = dense.clone().try_inverse().unwrap();
        let norm1 = |m: &DMatrix<f64>| {
            (0..m.ncols())
                .map(|c| m.column(c).abs().sum())
                .fold(0.0, f64::max)
        };
        let exact = norm1(&dense) * norm1(&inv);
        let est = lu.condition_estimate();
        assert!(
            est <= exact * (1.0 + 1e-9) && est >= exact / 3.0,
            "{est} vs {exact}"
        );
    }

    #[test]
    fn singular_matrix_reports_zero_pivot() {
        let mut lu = BandLu::zeros(3, 1, 1);
        lu.set(0, 0, 1.0);
        lu.set(0, 1, 2.0);
        lu.set(1, 0, 2.0);
        lu.set(1, 1, 4.0);
        lu.set(2, 2, 1.0);
        lu.factor();
        assert_eq!(lu.zero_pivot(), Some(1));
        assert!(lu.condition_estimate().is_infinite());
    }
}
