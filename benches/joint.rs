//! Throughput of the joint band-k filter and its smoother (docs/theory.md §8, §9) without I/O
//! (`cargo bench --bench joint`), on `bench/scattering.toml` (n = 2, K = 2, b = 15), in
//! subsystem-steps per second. Groups:
//! - `joint_filter`: N = 10, 30, 10², 10³, 10⁴ (time per element flat means linear in N), beside the
//!   two-step filter on the same chain, and the centralized filter for N ≤ 10²;
//! - `joint_smoother`: forward and backward pass, N = 10², 10³, 10⁴ (its ratio to the filter
//!   and its exponent in N; at N = 10⁴ a run takes seconds, so its ten samples take a minute);
//! - `joint_update`: the joint filter with Nahi's (`linear`) and the mixture update
//!   (docs/theory.md §10), N = 10³.
//!
//! Inputs are simulated once per size, outside the timed routine. Run with
//! `RAYON_NUM_THREADS=1` for one-core figures (the joint filter itself is sequential).

use criterion::{
    BatchSize, BenchmarkId, Criterion, SamplingMode, Throughput, criterion_group, criterion_main,
};
use sisfilt::config::ConfigSource;
use sisfilt::filter::{
    CentralizedFilter, ChainFilter, JointFilter, JointOptions, TwoStepOptions, Update, two_step,
};
use sisfilt::inputs::InputStream;
use sisfilt::model::Model;
use sisfilt::simulate::simulate;
use sisfilt::smoother::{JointSmoother, Smoother};

const STEPS: usize = 20;

fn chain(subsystems: usize) -> Model {
    let text = include_str!("../bench/scattering.toml")
        .replace("subsystems = 1000", &format!("subsystems = {subsystems}"))
        .replace("steps = 20", &format!("steps = {STEPS}"));
    Model::from_config(&ConfigSource::from_text("scattering.toml", ".".into(), text).unwrap())
        .unwrap()
}

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

fn run(f: &mut dyn ChainFilter, ys: &[Vec<f64>], us: &[Vec<f64>]) {
    for (y, u) in ys.iter().zip(us) {
        f.step(y, u).unwrap();
    }
}

fn joint_filter(c: &mut Criterion) {
    let mut g = c.benchmark_group("joint_filter");
    g.sample_size(10);
    for big_n in [10, 30, 100, 1000, 10_000] {
        let model = chain(big_n);
        let (ys, us) = data(&model);
        g.throughput(Throughput::Elements((big_n * STEPS) as u64));
        g.bench_with_input(BenchmarkId::new("joint", big_n), &big_n, |b, _| {
            b.iter_batched(
                || JointFilter::new(&model, JointOptions::default()).unwrap(),
                |mut f| run(&mut f, &ys, &us),
                BatchSize::LargeInput,
            )
        });
        g.bench_with_input(BenchmarkId::new("two-step", big_n), &big_n, |b, _| {
            b.iter_batched(
                || two_step(&model, TwoStepOptions::default()).unwrap(),
                |mut f| run(f.as_mut(), &ys, &us),
                BatchSize::LargeInput,
            )
        });
        if big_n <= 300 {
            g.bench_with_input(BenchmarkId::new("centralized", big_n), &big_n, |b, _| {
                b.iter_batched(
                    || CentralizedFilter::new(&model, false, 1000).unwrap(),
                    |mut f| run(&mut f, &ys, &us),
                    BatchSize::LargeInput,
                )
            });
        }
    }
    g.finish();
}

fn joint_smoother(c: &mut Criterion) {
    let mut g = c.benchmark_group("joint_smoother");
    g.sample_size(10);
    for big_n in [100, 1000, 10_000] {
        let model = chain(big_n);
        let (ys, us) = data(&model);
        g.throughput(Throughput::Elements((big_n * STEPS) as u64));
        if big_n >= 10_000 {
            g.sampling_mode(SamplingMode::Flat);
        }
        g.bench_with_input(BenchmarkId::new("joint-smoother", big_n), &big_n, |b, _| {
            b.iter_batched(
                || Box::new(JointSmoother::new(&model, JointOptions::default()).unwrap()),
                |mut s| {
                    for (y, u) in ys.iter().zip(&us) {
                        s.step(y, u).unwrap();
                    }
                    s.finish().unwrap()
                },
                BatchSize::LargeInput,
            )
        });
    }
    g.finish();
}

fn joint_update(c: &mut Criterion) {
    let mut g = c.benchmark_group("joint_update");
    g.sample_size(10);
    let big_n = 1000;
    let model = chain(big_n);
    let (ys, us) = data(&model);
    g.throughput(Throughput::Elements((big_n * STEPS) as u64));
    for (name, update) in [("linear", Update::Linear), ("mixture", Update::Mixture)] {
        let opts = JointOptions {
            update,
            ..JointOptions::default()
        };
        g.bench_function(BenchmarkId::new("joint", name), |b| {
            b.iter_batched(
                || JointFilter::new(&model, opts).unwrap(),
                |mut f| run(&mut f, &ys, &us),
                BatchSize::LargeInput,
            )
        });
    }
    g.finish();
}

criterion_group!(benches, joint_filter, joint_smoother, joint_update);
criterion_main!(benches);
