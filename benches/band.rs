//! Block-band kernels of docs/theory.md §8 (`cargo bench --bench band`) at the joint filter's working
//! point: `nb = 1000` blocks of `bs = 2`, band `k = 2`, `A_eff` half-width `b = 16` (so the
//! predict step extends the posterior to `w = k + 2b = 34`). Throughput is in block rows;
//! flops per block row (leading terms): sandwich `2bs³(2b+1)(k+2b+2)`, selected inversion
//! `2wk bs³`, Cholesky `(k²/2 + 2k) bs³`, completion `≈ ((k+1)bs)³ · 2/3`. Times are the
//! benchmarking thread's CPU time, not wall time (the machine is shared).

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sisfilt::linalg::band::{
    BandCholesky, CompletionWorkspace, GenBand, SandwichWorkspace, SymBand, completion_precision,
    sandwich,
};
use sisfilt::linalg::band_lu::{BandLu, SplitBandLu};
use std::time::Duration;

const NB: usize = 1000;
const BS: usize = 2;
const K: usize = 2;
const B: usize = 16;

/// A diagonally dominant (so positive definite) symmetric band of width `k`.
fn band_spd(rng: &mut ChaCha8Rng) -> SymBand {
    let mut s = SymBand::zeros(NB, BS, K);
    for i in 0..NB {
        for d in 0..=K.min(NB - 1 - i) {
            for v in s.block_mut(i, d) {
                *v = rng.random_range(-1.0..=1.0);
            }
        }
        let blk = s.block_mut(i, 0);
        let t = blk[1];
        blk[2] = t;
        blk[0] = 4.0 * (K as f64 + 1.0) * BS as f64;
        blk[3] = blk[0];
    }
    s
}

/// CPU time of the benchmarking thread (`CLOCK_THREAD_CPUTIME_ID`): on a machine shared with
/// other builds, wall time also counts the time this thread waits for a core.
struct ThreadCpuTime {
    wall: WallTime,
}

fn thread_cpu_now() -> Duration {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0, "clock_gettime(CLOCK_THREAD_CPUTIME_ID)");
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}

impl Measurement for ThreadCpuTime {
    type Intermediate = Duration;
    type Value = Duration;
    fn start(&self) -> Duration {
        thread_cpu_now()
    }
    fn end(&self, start: Duration) -> Duration {
        thread_cpu_now() - start
    }
    fn add(&self, a: &Duration, b: &Duration) -> Duration {
        *a + *b
    }
    fn zero(&self) -> Duration {
        Duration::ZERO
    }
    fn to_f64(&self, v: &Duration) -> f64 {
        v.as_nanos() as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        self.wall.formatter()
    }
}

fn cpu_time() -> Criterion<ThreadCpuTime> {
    Criterion::default().with_measurement(ThreadCpuTime { wall: WallTime })
}

fn bench(c: &mut Criterion<ThreadCpuTime>) {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let lambda = band_spd(&mut rng);
    let w = K + 2 * B;
    let mut chol = BandCholesky::new(NB, BS, K);
    chol.factor(&lambda).unwrap();
    let mut p = SymBand::zeros(NB, BS, w);
    chol.selected_inverse(&mut p);
    let mut a = GenBand::zeros(NB, BS, B);
    for i in 0..NB {
        for j in i.saturating_sub(B)..(i + B + 1).min(NB) {
            let decay = 0.5f64.powi(i.abs_diff(j) as i32);
            for v in a.block_mut(i, j) {
                *v = decay * rng.random_range(-1.0..=1.0);
            }
        }
    }

    let mut group = c.benchmark_group("band");
    group.throughput(Throughput::Elements(NB as u64));
    let id = |name: &str| BenchmarkId::new(name, format!("nb{NB}_bs{BS}_k{K}_b{B}"));

    let mut out_k = SymBand::zeros(NB, BS, K);
    let mut ws = CompletionWorkspace::new(NB, BS, K);
    group.bench_function(id("completion_precision"), |bch| {
        bch.iter(|| completion_precision(&p, K, &mut out_k, &mut ws).unwrap())
    });
    group.bench_function(id("cholesky_factor"), |bch| {
        bch.iter(|| chol.factor(&lambda).unwrap())
    });
    let mut x: Vec<f64> = (0..NB * BS).map(|r| (r as f64).sin()).collect();
    group.bench_function(id("solve_in_place"), |bch| {
        bch.iter(|| chol.solve_in_place(&mut x))
    });
    let mut out_w = SymBand::zeros(NB, BS, w);
    group.bench_function(id("selected_inverse_w34"), |bch| {
        bch.iter(|| chol.selected_inverse(&mut out_w))
    });
    let mut out_kk = SymBand::zeros(NB, BS, K);
    group.bench_function(id("selected_inverse_w2"), |bch| {
        bch.iter(|| chol.selected_inverse(&mut out_kk))
    });
    let mut sw = SandwichWorkspace::new(NB, BS, B, K);
    group.bench_function(id("sandwich"), |bch| {
        bch.iter(|| sandwich(&a, &p, &mut out_k, &mut sw))
    });
    group.finish();
}

/// The step-1 solve of a chain of 10⁴ subsystems with `n⁺ = n⁻ = 1` (docs/theory.md §2):
/// `kl = ku = 2`, `2 (N − 1)` rows, whole and split at the middle; the split's two blocks
/// one after the other and side by side on one thread ([`BandLu::solve_each`]). Throughput
/// in rows.
fn chain(c: &mut Criterion<ThreadCpuTime>) {
    let (n, kl, ku) = (2 * (10_000 - 1), 2, 2);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut lu = BandLu::zeros(n, kl, ku);
    for r in 0..n {
        for c in r.saturating_sub(kl)..(r + ku + 1).min(n) {
            let v = if r == c {
                1.0
            } else {
                0.2 * rng.random_range(-1.0..=1.0)
            };
            lu.set(r, c, v);
        }
    }
    let split = SplitBandLu::new(&lu, n / 2, 1e8).expect("a well-conditioned split");
    lu.factor();
    let mut x: Vec<f64> = (0..n).map(|r| (r as f64).sin()).collect();
    let mut group = c.benchmark_group("chain_solve");
    group.throughput(Throughput::Elements(n as u64));
    group.bench_function("whole", |bch| bch.iter(|| lu.solve(&mut x)));
    let (x1, x2) = x.split_at_mut(n / 2);
    group.bench_function("blocks_one_after_the_other", |bch| {
        bch.iter(|| {
            split.solve_block(false, x1);
            split.solve_block(true, x2);
        })
    });
    group.bench_function("blocks_side_by_side", |bch| {
        bch.iter(|| split.solve_blocks(x1, x2))
    });
    group.finish();
}

criterion_group! {
    name = benches;
    config = cpu_time();
    targets = bench, chain
}
criterion_main!(benches);
