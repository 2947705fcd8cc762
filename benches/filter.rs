//! Throughput of the filter cores without I/O, in subsystem-steps per second
//! (`cargo bench --bench filter`). Workload of issue 5: n = 2, q = 1, m = 1, n⁺ = n⁻ = 1.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use sisfilt::config::ConfigSource;
use sisfilt::filter::{ChainFilter, TwoStepFilter, TwoStepOptions, two_step};
use sisfilt::inputs::InputStream;
use sisfilt::model::Model;
use sisfilt::simulate::simulate;

/// The benchmark chain: a stable second-order subsystem with scattering coupling.
pub fn workload(subsystems: usize, steps: usize) -> Model {
    let text = format!(
        "subsystems = {subsystems}\nsteps = {steps}\nseed = 1\n\
         [interconnection]\nplus = 1\nminus = 1\n\
         [model]\nA = [[0.9, 0.1], [-0.1, 0.8]]\nB = [[0.1, 0.05], [0.05, 0.1]]\n\
         C = [[0.0], [0.1]]\nD = [[0.3, 0.1], [0.1, 0.3]]\nG = [[0.1, 0.2], [0.2, 0.1]]\n\
         J = [[1.0, 0.0]]\nM = [[0.1]]\nQ = [[0.01, 0.0], [0.0, 0.01]]\n\
         [dropout]\np = 0.8\n[initial]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n\
         [input]\nkind = \"sine\"\nperiod = 50.0\nphase = 0.1\n"
    );
    Model::from_config(&ConfigSource::from_text("bench", ".".into(), text).unwrap()).unwrap()
}

fn data(model: &Model) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let (mut ys, mut us) = (Vec::new(), Vec::new());
    let mut inputs = InputStream::open(model, None).unwrap();
    simulate(model, model.steps, 1, &mut inputs, |s| {
        ys.push(s.y.to_vec());
        us.push(s.u.to_vec());
        Ok(())
    })
    .unwrap();
    (ys, us)
}

fn distributed(c: &mut Criterion) {
    let mut group = c.benchmark_group("distributed");
    group.sample_size(10);
    for &n_sub in &[100usize, 1000, 10_000] {
        let steps = 20;
        let model = workload(n_sub, steps);
        let (ys, us) = data(&model);
        group.throughput(Throughput::Elements((n_sub * steps) as u64));
        group.bench_with_input(BenchmarkId::new("fixed", n_sub), &n_sub, |b, _| {
            b.iter_batched(
                || two_step(&model, TwoStepOptions::default()).unwrap(),
                |mut f| {
                    for (y, u) in ys.iter().zip(&us) {
                        f.step(y, u).unwrap();
                    }
                    f
                },
                criterion::BatchSize::LargeInput,
            )
        });
        group.bench_with_input(BenchmarkId::new("dynamic", n_sub), &n_sub, |b, _| {
            b.iter_batched(
                || TwoStepFilter::new(&model, TwoStepOptions::default()).unwrap(),
                |mut f| {
                    for (y, u) in ys.iter().zip(&us) {
                        f.step(y, u).unwrap();
                    }
                    f
                },
                criterion::BatchSize::LargeInput,
            )
        });
    }
    group.finish();
}

criterion_group!(benches, distributed);
criterion_main!(benches);
