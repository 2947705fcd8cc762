//! Throughput of the filter cores without I/O (`cargo bench --bench filter`), on workload W of
//! issue 5 (`bench/workload.toml`: n = 2, q = 1, m = 1, n⁺ = n⁻ = 1) with its chain length
//! and horizon changed per benchmark. Groups:
//! - `core`: the distributed filter on W (N = 10⁴) with one and with two threads, in
//!   subsystem-steps per second: `threads` from a fresh filter every 20 steps, `steady` one
//!   filter stepping on (the measurements of the 20 steps over again);
//! - `scaling`: N = 10²…10⁵ on one thread, for the linear-scaling fit (time per element flat);
//! - `sharing`: the shared covariance recursions against per-subsystem ones (`local`, `paper`);
//! - `centralized_vs_distributed`: time per step for N = 10, 30, 100, 300 (elements = steps);
//! - `update`: the distributed filter with Nahi's (`linear`) and the mixture update
//!   (docs/theory.md §10) on W (N = 10⁴), one thread.
//!
//! Inputs are simulated once per size, outside the timed routine (`iter_batched` builds a
//! fresh filter per batch).

use criterion::{BatchSize, BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use sisfilt::config::ConfigSource;
use sisfilt::filter::kernel::FixedKernel;
use sisfilt::filter::{
    CentralizedFilter, ChainFilter, SecondMoment, TwoStepFilter, TwoStepOptions, Update, two_step,
};
use sisfilt::inputs::InputStream;
use sisfilt::model::Model;
use sisfilt::simulate::simulate;

/// The kernel `two_step` picks for W.
type Fast = TwoStepFilter<FixedKernel<2, 1>>;

/// Workload W with `subsystems` and `steps` replaced.
fn workload(subsystems: usize, steps: usize) -> Model {
    let text = include_str!("../bench/workload.toml")
        .replace("subsystems = 10000", &format!("subsystems = {subsystems}"))
        .replace("steps = 1000", &format!("steps = {steps}"));
    Model::from_config(&ConfigSource::from_text("workload.toml", ".".into(), text).unwrap())
        .unwrap()
}

/// Simulated measurements and inputs of every step.
fn data(model: &Model) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let (mut ys, mut us) = (Vec::new(), Vec::new());
    let mut inputs = InputStream::open(model, None).unwrap();
    simulate(model, model.horizon().unwrap(), 1, &mut inputs, |s| {
        ys.push(s.y.to_vec());
        us.push(s.u.to_vec());
        Ok(())
    })
    .unwrap();
    (ys, us)
}

fn run<F: ChainFilter + ?Sized>(f: &mut F, ys: &[Vec<f64>], us: &[Vec<f64>]) {
    for (y, u) in ys.iter().zip(us) {
        f.step(y, u).unwrap();
    }
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

fn core(c: &mut Criterion) {
    let (n_sub, steps) = (10_000, 20);
    let model = workload(n_sub, steps);
    let (ys, us) = data(&model);
    let mut group = c.benchmark_group("core");
    group.sample_size(20);
    group.throughput(Throughput::Elements((n_sub * steps) as u64));
    for threads in [1, 2] {
        let pool = pool(threads);
        group.bench_with_input(BenchmarkId::new("threads", threads), &threads, |b, _| {
            pool.install(|| {
                b.iter_batched(
                    || Fast::with_kernel(&model, TwoStepOptions::default()).unwrap(),
                    |mut f| {
                        run(&mut f, &ys, &us);
                        f
                    },
                    BatchSize::LargeInput,
                )
            })
        });
        // One filter stepping on, as in a run: its arrays in memory and the pool's threads
        // awake, which a fresh filter every 20 steps pays for again each time.
        group.bench_with_input(BenchmarkId::new("steady", threads), &threads, |b, _| {
            pool.install(|| {
                let mut f = Fast::with_kernel(&model, TwoStepOptions::default()).unwrap();
                run(&mut f, &ys, &us);
                b.iter(|| run(&mut f, &ys, &us))
            })
        });
    }
    group.finish();
}

fn scaling(c: &mut Criterion) {
    let mut group = c.benchmark_group("scaling");
    group.sample_size(10);
    let pool = pool(1);
    for n_sub in [100usize, 1_000, 10_000, 100_000] {
        let steps = (1_000_000 / n_sub).clamp(10, 1000);
        let model = workload(n_sub, steps);
        let (ys, us) = data(&model);
        group.throughput(Throughput::Elements((n_sub * steps) as u64));
        group.bench_with_input(BenchmarkId::new("N", n_sub), &n_sub, |b, _| {
            pool.install(|| {
                b.iter_batched(
                    || Fast::with_kernel(&model, TwoStepOptions::default()).unwrap(),
                    |mut f| {
                        run(&mut f, &ys, &us);
                        f
                    },
                    BatchSize::LargeInput,
                )
            })
        });
    }
    group.finish();
}

fn sharing(c: &mut Criterion) {
    let (n_sub, steps) = (10_000, 20);
    let model = workload(n_sub, steps);
    let (ys, us) = data(&model);
    let mut group = c.benchmark_group("sharing");
    group.sample_size(10);
    group.throughput(Throughput::Elements((n_sub * steps) as u64));
    let pool = pool(1);
    for (name, second_moment) in [
        ("local", SecondMoment::Local),
        ("paper", SecondMoment::Paper),
    ] {
        let opts = TwoStepOptions {
            second_moment,
            ..TwoStepOptions::default()
        };
        for shared in [true, false] {
            let id = BenchmarkId::new(name, if shared { "shared" } else { "per-subsystem" });
            group.bench_function(id, |b| {
                pool.install(|| {
                    b.iter_batched(
                        || {
                            let f = Fast::with_kernel(&model, opts).unwrap();
                            if shared { f } else { f.without_sharing() }
                        },
                        |mut f| {
                            run(&mut f, &ys, &us);
                            f
                        },
                        BatchSize::LargeInput,
                    )
                })
            });
        }
    }
    group.finish();
}

fn centralized_vs_distributed(c: &mut Criterion) {
    let mut group = c.benchmark_group("centralized_vs_distributed");
    group.sample_size(10);
    for n_sub in [10usize, 30, 100, 300] {
        let steps = match n_sub {
            300 => 2,
            100 => 5,
            _ => 20,
        };
        let model = workload(n_sub, steps);
        let (ys, us) = data(&model);
        // Elements are time steps: the report reads in steps per second.
        group.throughput(Throughput::Elements(steps as u64));
        group.bench_with_input(BenchmarkId::new("distributed", n_sub), &n_sub, |b, _| {
            b.iter_batched(
                || two_step(&model, TwoStepOptions::default()).unwrap(),
                |mut f| {
                    run(f.as_mut(), &ys, &us);
                    f
                },
                BatchSize::LargeInput,
            )
        });
        group.bench_with_input(BenchmarkId::new("centralized", n_sub), &n_sub, |b, _| {
            b.iter_batched(
                || CentralizedFilter::new(&model, false, 1000).unwrap(),
                |mut f| {
                    run(&mut f, &ys, &us);
                    f
                },
                BatchSize::LargeInput,
            )
        });
    }
    group.finish();
}

fn update(c: &mut Criterion) {
    let (n_sub, steps) = (10_000, 20);
    let model = workload(n_sub, steps);
    let (ys, us) = data(&model);
    let mut group = c.benchmark_group("update");
    group.sample_size(20);
    group.throughput(Throughput::Elements((n_sub * steps) as u64));
    let pool = pool(1);
    for (name, update) in [("linear", Update::Linear), ("mixture", Update::Mixture)] {
        let opts = TwoStepOptions {
            update,
            ..TwoStepOptions::default()
        };
        group.bench_function(BenchmarkId::new("distributed", name), |b| {
            pool.install(|| {
                b.iter_batched(
                    || Fast::with_kernel(&model, opts).unwrap(),
                    |mut f| {
                        run(&mut f, &ys, &us);
                        f
                    },
                    BatchSize::LargeInput,
                )
            })
        });
    }
    group.finish();
}

criterion_group!(
    benches,
    core,
    scaling,
    sharing,
    centralized_vs_distributed,
    update
);
criterion_main!(benches);
