//! The verdict of the innovation check (docs/theory.md §14) on inputs whose answer is known:
//! innovation sequences constructed here, fed to the check as the measurements of a model
//! whose prediction is zero; a recording without dropouts read with a `p` below 1; a fit of
//! the noise levels of a model that misses a state.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use sisfilt::filter::{Dropouts, FilterKind, Update};
use sisfilt::fit::{FitSpec, ParamGroup, fit};
use sisfilt::innovations::{Cause, InnovationCheck};
use sisfilt::run::{RunSpec, estimate};

use crate::common::{model_from, shipped_config, simulate_run};

/// The shipped platoon with `p` and, where given, the number of subsystems replaced.
fn platoon(p: f64, subsystems: Option<usize>) -> sisfilt::model::Model {
    let text = std::fs::read_to_string(shipped_config("platoon.toml")).unwrap();
    let mut changed = text.replace("p = 0.85", &format!("p = {p:?}"));
    if let Some(n) = subsystems {
        changed = changed.replace("subsystems = 20", &format!("subsystems = {n}"));
    }
    assert_ne!(changed, text);
    model_from(&changed)
}

/// `N` scalar subsystems whose prediction is zero with a zero covariance and `M = 1`: with
/// known dropouts each measurement is its own standardised innovation.
fn unit_chain(subsystems: usize) -> sisfilt::model::Model {
    model_from(&format!(
        "subsystems = {subsystems}\nsteps = 400\n\
         [interconnection]\nplus = 1\nminus = 1\n\
         [model]\nA = [[0.0]]\nB = [[0.0, 0.0]]\nD = [[0.0], [0.0]]\nG = [[0.0, 0.0], [0.0, 0.0]]\n\
         J = [[1.0]]\nM = [[1.0]]\nQ = [[1.0]]\n\
         [dropout]\np = 1.0\n\
         [initial]\nmean = [0.0]\ncov = [[0.0]]\n"
    ))
}

/// The verdict on `steps` × `N` innovations, series `s` being `scale · (c₀ e_t + c₁ e_{t−1} +
/// …)` of white `e` normalised to unit variance, or an AR(1) with coefficient `phi`.
fn verdict_of(
    subsystems: usize,
    steps: usize,
    scale: f64,
    ma: &[f64],
    phi: f64,
) -> (Vec<Cause>, Vec<String>) {
    let model = unit_chain(subsystems);
    let mut check = InnovationCheck::new(&model, Dropouts::Known, Update::Linear, false);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let gain = (ma.iter().map(|c| c * c).sum::<f64>() / (1.0 - phi * phi)).sqrt();
    let mut past = vec![vec![0.0; ma.len()]; subsystems];
    let mut ar = vec![0.0; subsystems];
    let (zeros, none) = (vec![0.0; subsystems], Vec::new());
    // A burn-in, so that the AR(1) starts stationary.
    for t in 1..=steps + 50 {
        let y: Vec<f64> = (0..subsystems)
            .map(|i| {
                past[i].rotate_right(1);
                past[i][0] = StandardNormal.sample(&mut rng);
                let ma_value: f64 = ma.iter().zip(&past[i]).map(|(c, e)| c * e).sum();
                ar[i] = phi * ar[i] + ma_value;
                scale * ar[i] / gain
            })
            .collect();
        if t > 50 {
            check.step(t - 50, &zeros, &zeros, None, &y, &none).unwrap();
        }
    }
    let report = check.report();
    (report.verdict.clone(), report.warnings())
}

/// Each rule of the verdict's table, and the portmanteau's own cause: a lag-1
/// autocorrelation of +0.22 and a lag-2 one of −0.24 that cancel in the Bartlett-weighted sum
/// (`c = [1, 0.3857, −0.3]`: `γ₁ + 0.9 γ₂ = 0`) are the model's form, named with their lags;
/// so is an oscillation whose lag 1 is positive and whose weighted sum is negative (a
/// thermistor chain's internal waves), which no noise level makes.
#[test]
fn each_rule_names_its_cause_on_constructed_innovations() {
    // (name, scale, MA coefficients, AR coefficient, the causes)
    type Case<'a> = (&'a str, f64, &'a [f64], f64, &'a [Cause]);
    let cases: [Case; 9] = [
        ("white", 1.0, &[1.0], 0.0, &[]),
        ("correlated", 1.0, &[1.0], 0.3, &[Cause::QTooSmall]),
        ("alternating", 1.0, &[1.0], -0.3, &[Cause::QTooLarge]),
        ("large, correlated", 1.3, &[1.0], 0.3, &[Cause::QTooSmall]),
        ("large, white", 1.3, &[1.0], 0.0, &[Cause::MTooSmall]),
        ("small, alternating", 0.7, &[1.0], -0.3, &[Cause::QTooLarge]),
        ("small, correlated", 0.7, &[1.0], 0.3, &[Cause::MTooLarge]),
        ("small, white", 0.7, &[1.0], 0.0, &[Cause::MOrQTooLarge]),
        // γ₁ = +0.3, γ₂ = −0.59, γ₃ = −0.3: the weighted sum is negative, lag 1 positive.
        (
            "oscillating",
            1.0,
            &[1.0, 0.3, -0.5, -0.3],
            0.0,
            &[Cause::Form],
        ),
    ];
    for (name, scale, ma, phi, want) in cases {
        let (causes, _) = verdict_of(50, 400, scale, ma, phi);
        assert_eq!(causes, want, "{name}");
    }
    let (causes, warnings) = verdict_of(50, 400, 1.0, &[1.0, 0.3857, -0.3], 0.0);
    assert_eq!(causes, [Cause::Form]);
    assert_eq!(warnings.len(), 1);
    let w = &warnings[0];
    assert!(
        w.contains("the innovations are not white (Q_acf")
            && w.contains("at lag 1 (z +")
            && w.contains(", 2 (z -")
            && w.contains(", ρ -0.2")
            && w.ends_with("(its form, not its noise levels)"),
        "{w}"
    );
}

/// A recording whose only missing values are gaps (simulated with `p = 1`, then cells
/// emptied), read with `p = 0.9`: the wrong `p` leads the verdict, its warning says that more
/// readings arrived than `p` says and that, with the gaps counted as the only losses, `p = 1`
/// fits; the warnings after it say they may follow from it.
#[test]
fn a_recording_without_dropouts_read_with_p_below_one_says_so() {
    let truth = platoon(1.0, None);
    let model = platoon(0.9, None);
    let run = simulate_run(&truth, 3);
    let mut y = run.y.concat();
    let gaps = y.iter_mut().step_by(17).map(|v| *v = f64::NAN).count();
    let spec = RunSpec {
        filter: FilterKind::Joint,
        ..RunSpec::default()
    };
    let est = estimate(
        &model,
        &spec.check().unwrap(),
        &y,
        Some(&run.u.concat()),
        None,
    )
    .unwrap();
    let report = est.report.summary.innovations.unwrap();
    assert_eq!(report.gaps, gaps as u64);
    assert_eq!(report.verdict.first(), Some(&Cause::PWrong), "{report:?}");
    let warnings = report.warnings();
    assert!(
        warnings[0].contains("p is likely higher than 0.900")
            && warnings[0].contains(&format!("the only losses are the {gaps} gaps")),
        "{warnings:?}"
    );
    assert!(warnings.len() > 1, "{warnings:?}");
    for w in &warnings[1..] {
        assert!(
            w.ends_with("(this may follow from the wrong p: set p first)"),
            "{w}"
        );
    }
}

/// Noise levels fitted to a model that misses a state (each sensor's noise an AR(1) with
/// coefficient −0.8, which the model takes as white, and no noise level of its own makes): after the fit no cause names `Q` or
/// `M`; the misfit is the model's form, and the warning says it is left after fitting them.
#[test]
fn a_misfit_left_after_fitting_q_and_m_is_the_models_form() {
    let truth = platoon(1.0, Some(6));
    let run = simulate_run(&truth, 7);
    let q = truth.dims.q;
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut colour = vec![0.0; truth.subsystems * q];
    let y: Vec<f64> = run
        .y
        .iter()
        .flat_map(|row| {
            colour.iter_mut().for_each(|c| {
                *c = -0.8 * *c + 0.12 * Distribution::<f64>::sample(&StandardNormal, &mut rng);
            });
            row.iter()
                .zip(&colour)
                .map(|(v, c)| v + c)
                .collect::<Vec<f64>>()
        })
        .collect();
    let spec = FitSpec {
        params: vec![ParamGroup::Q, ParamGroup::M],
        filter: FilterKind::Centralized,
        dropouts: Dropouts::Known,
        ..FitSpec::default()
    }
    .check()
    .unwrap();
    let fitted = fit(&truth, &spec, &y, Some(&run.u.concat()), None).unwrap();
    let report = fitted.report.innovations.expect("the fitted model's check");
    assert!(
        report.verdict.contains(&Cause::Form),
        "{:?}",
        report.verdict
    );
    for cause in [
        Cause::QTooSmall,
        Cause::QTooLarge,
        Cause::MTooSmall,
        Cause::MTooLarge,
        Cause::MOrQTooLarge,
    ] {
        assert!(!report.verdict.contains(&cause), "{:?}", report.verdict);
    }
    let warnings = report.warnings();
    assert!(
        warnings.iter().any(
            |w| w.contains("left after fitting Q and M, the misfit is one of the model's form")
        ),
        "{warnings:?}"
    );
}
