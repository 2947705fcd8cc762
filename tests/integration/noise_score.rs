//! The gradient of the exact log-likelihood with respect to each subsystem's noise variances
//! (docs/theory.md §16, "Each subsystem's own noise") against central differences of the
//! dense Gaussian density of all the measurements, built in the test.

use sisfilt::filter::centralized::CentralizedLimits;
use sisfilt::fit::noise_score;
use sisfilt::smoother::score::ScoreParts;

use crate::common::{model_from, simulate_run};
use crate::reference_filters::{CHAIN, dense_log_density};

#[test]
fn the_noise_score_is_the_derivative_of_the_dense_density() {
    // A coupled chain (G, H, inputs, R, an off-diagonal M, a window whose A and G differ),
    // every reading arriving, some elements missing.
    let base = model_from(&CHAIN.replace("p = [0.9, 0.6, 0.8, 0.7]", "p = 1.0"));
    let q_values = [0.03, 0.02, 0.05, 0.01, 0.02, 0.04, 0.06, 0.03];
    let m_values = [0.2, 0.3, 0.25, 0.35, 0.15, 0.4, 0.3, 0.2];
    let at = |q: &[f64], m: &[f64]| {
        base.with_diagonals_per_subsystem("Q", q)
            .with_diagonals_per_subsystem("M", m)
    };
    let model = at(&q_values, &m_values);
    let run = simulate_run(&model, 5);
    let ys: Vec<Vec<f64>> = run
        .y
        .iter()
        .enumerate()
        .map(|(t, y)| {
            y.iter()
                .enumerate()
                .map(|(k, &v)| if (3 * t + k) % 7 == 0 { f64::NAN } else { v })
                .collect()
        })
        .collect();
    let flat_y: Vec<f64> = ys.concat();
    let flat_u: Vec<f64> = run.u.concat();
    let both = ScoreParts { q: true, m: true };
    let score = noise_score(
        &model,
        CentralizedLimits::from(1000),
        both,
        &flat_y,
        Some(&flat_u),
    )
    .unwrap();
    let dense = dense_log_density(&model, &ys, &run.u);
    assert!(
        (score.log_likelihood - dense).abs() < 1e-9 * dense.abs(),
        "ℓ {} vs dense {dense}",
        score.log_likelihood
    );
    let numeric = |q: &[f64], m: &[f64], k: usize, of_q: bool| {
        let value = if of_q { q[k] } else { m[k] };
        let h = 1e-4 * value;
        let moved = |step: f64| {
            let (mut q, mut m) = (q.to_vec(), m.to_vec());
            if of_q {
                q[k] += step;
            } else {
                m[k] += step;
            }
            dense_log_density(&at(&q, &m), &ys, &run.u)
        };
        (moved(h) - moved(-h)) / (2.0 * h)
    };
    let scale = score
        .q
        .iter()
        .chain(&score.m)
        .fold(0.0f64, |a, v| a.max(v.abs()));
    assert!(scale > 1.0, "the gradient is not trivially small: {scale}");
    for k in 0..8 {
        for (of_q, analytic) in [(true, score.q[k]), (false, score.m[k])] {
            let expected = numeric(&q_values, &m_values, k, of_q);
            assert!(
                (analytic - expected).abs() < 1e-6 * scale,
                "{}[{k}]: {analytic} vs central differences {expected}",
                if of_q { "Q" } else { "M" }
            );
        }
    }
    // Each part alone is the same.
    let q_only = noise_score(
        &model,
        CentralizedLimits::from(1000),
        ScoreParts { q: true, m: false },
        &flat_y,
        Some(&flat_u),
    )
    .unwrap();
    assert_eq!(q_only.q, score.q);
    assert!(q_only.m.is_empty());
}
