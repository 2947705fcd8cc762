//! Initial conditions per subsystem (an override's `initial.mean`, `initial.cov`, or a mean per
//! subsystem in `[initial]`): read as
//! written, refused with the key named, drawn by `simulate`, and taken by every filter as the
//! dense references written in the tests take them (the log density of all measurements, the
//! batch smoother, the centralized filter at full band, a decoupled chain's own filters).

use std::path::Path;

use sisfilt::filter::{ChainFilter, JointFilter, JointOptions, SecondMoment};
use sisfilt::model::Model;

use crate::common::{model_from, simulate_run};
use crate::reference_filters::{CHAIN, assert_centralized_known_log_likelihood_is_dense};

/// Overrides that start the subsystems of a chain of at least 3 (`n = 2`) apart: 2 and 3 from
/// another mean, then 1 and 3 with another covariance (the later override wins, and keeps
/// the mean the earlier one gave 3).
pub const OWN_STARTS: &str = "
[[override]]
subsystems = [2, 3]
initial.mean = [2.0, -1.0]

[[override]]
subsystems = [[1, 1], [3, 3]]
initial.cov = [[0.05, 0.01], [0.01, 0.3]]
";

#[test]
fn each_subsystem_starts_from_what_its_overrides_say() {
    let model = model_from(&format!("{CHAIN}{OWN_STARTS}"));
    let (base_mean, base_cov) = ([1.0, -0.5], [0.8, 0.1, 0.1, 0.6]);
    let (own_mean, own_cov) = ([2.0, -1.0], [0.05, 0.01, 0.01, 0.3]);
    let expected: [(&[f64], &[f64]); 4] = [
        (&base_mean, &own_cov),
        (&own_mean, &base_cov),
        (&own_mean, &own_cov),
        (&base_mean, &base_cov),
    ];
    for (i, (mean, cov)) in expected.iter().enumerate() {
        let start = model.initial.of(i);
        assert_eq!(start.mean.as_slice(), *mean, "subsystem {}", i + 1);
        assert_eq!(start.cov.as_slice(), *cov, "subsystem {}", i + 1);
    }
    assert_eq!(model.initial.sets().len(), 4);
    assert!(!model.initial.shared());
    let varying = sisfilt::check::check(&model).unwrap().varying;
    assert!(
        varying
            .iter()
            .any(|v| v.key == "initial" && v.space && !v.time)
    );
    // One override for the whole chain: one start again.
    let all = model_from(&format!(
        "{CHAIN}\n[[override]]\ninitial.mean = [0.0, 0.0]\n"
    ));
    assert!(all.initial.shared());
    assert_eq!(all.initial.of(3).mean.as_slice(), &[0.0, 0.0]);
}

/// `[initial] mean` as one list per subsystem is the same chain as one override per subsystem.
#[test]
fn a_mean_per_subsystem_is_one_override_per_subsystem() {
    let means = [[1.0, -0.5], [2.0, 0.0], [2.0, 0.0], [-1.0, 0.25]];
    let listed = CHAIN.replace(
        "mean = [1.0, -0.5]",
        "mean = [[1.0, -0.5], [2.0, 0.0], [2.0, 0.0], [-1.0, 0.25]]",
    );
    let mut overridden = CHAIN.to_string();
    for (i, m) in means.iter().enumerate() {
        overridden += &format!(
            "\n[[override]]\nsubsystems = [{0}, {0}]\ninitial.mean = [{1:?}, {2:?}]\n",
            i + 1,
            m[0],
            m[1]
        );
    }
    let (a, b) = (model_from(&listed), model_from(&overridden));
    assert_eq!(a.initial, b.initial);
    assert_eq!(a.initial.sets().len(), 3);
    for (i, m) in means.iter().enumerate() {
        assert_eq!(a.initial.of(i).mean.as_slice(), m);
    }
    assert_eq!(simulate_run(&a, 4).x, simulate_run(&b, 4).x);
    let cases = [
        (
            "mean = [[1.0, -0.5], [2.0, 0.0]]",
            "initial.mean",
            "4 lists of 2 values (one per subsystem), found 2 lists",
        ),
        (
            "mean = [[1.0, -0.5], [2.0, 0.0], [2.0], [0.0, 0.0]]",
            "initial.mean[3]",
            "expected 2 values",
        ),
    ];
    for (mean, key, what) in cases {
        let text = CHAIN.replace("mean = [1.0, -0.5]", mean);
        let err = Model::from_toml_str("chain.toml", Path::new("."), &text).unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.starts_with(&format!("chain.toml: {key}: ")), "{msg}");
        assert!(msg.contains(what), "{msg}");
        assert_eq!(err.exit_code(), 2);
    }
    let mixed = CHAIN.replace("mean = [1.0, -0.5]", "mean = [1.0, [2.0, 0.0]]");
    let msg = format!(
        "{:#}",
        Model::from_toml_str("chain.toml", Path::new("."), &mixed).unwrap_err()
    );
    assert!(msg.contains("not both"), "{msg}");
}

/// Each refusal names the file and the key, exit code 2.
#[test]
fn a_wrong_initial_override_is_refused_naming_its_key() {
    let cases = [
        (
            "subsystems = [2, 2]\nsteps = [1, 1]\ninitial.mean = [0.0, 0.0]",
            "override[2].steps",
            "leave out steps",
        ),
        (
            "subsystems = [2, 2]\ninitial.mean = [0.0, 0.0, 1.0]",
            "override[2].initial.mean",
            "expected 2 values",
        ),
        (
            "initial.cov = [[1.0, 0.0], [0.0, -1.0]]",
            "override[2].initial.cov",
            "semidefinite",
        ),
        ("initial.cov = [[1.0]]", "override[2].initial.cov", "2 × 2"),
    ];
    for (table, key, what) in cases {
        let text = format!("{CHAIN}\n[[override]]\n{table}\n");
        let err = Model::from_toml_str("chain.toml", Path::new("."), &text).unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.starts_with(&format!("chain.toml: {key}: ")), "{msg}");
        assert!(msg.contains(what), "{msg}");
        assert_eq!(err.exit_code(), 2);
    }
    let text = format!("{CHAIN}\n[[override]]\ninitial.covariance = [[1.0, 0.0], [0.0, 1.0]]\n");
    let err = Model::from_toml_str("chain.toml", Path::new("."), &text).unwrap_err();
    let msg = format!("{err:#}");
    assert!(msg.contains("covariance"), "{msg}");
    assert_eq!(err.exit_code(), 2);
}

/// A start with zero covariance is the state itself: `x(1, i)` equals its mean exactly, while
/// the others are drawn.
#[test]
fn simulate_draws_each_subsystem_from_its_own_start() {
    let model = model_from(&format!(
        "{CHAIN}\n[[override]]\nsubsystems = [3, 3]\ninitial.mean = [4.0, -2.0]\ninitial.cov = [[0.0, 0.0], [0.0, 0.0]]\n"
    ));
    let x1 = &simulate_run(&model, 3).x[0];
    assert_eq!(&x1[4..6], &[4.0, -2.0]);
    assert!((0..4).chain(6..8).all(|k| x1[k] != 1.0 && x1[k] != -0.5));
}

/// The centralized known-dropout filter's log-likelihood is the dense log density of all
/// received measurements, whose prior the test builds from each subsystem's own start.
#[test]
fn centralized_log_likelihood_is_the_dense_density_with_own_starts() {
    assert_centralized_known_log_likelihood_is_dense(&model_from(&format!("{CHAIN}{OWN_STARTS}")));
}

/// The centralized smoother against the batch estimator (all states conditioned on all
/// measurements, its prior from each subsystem's own start), in both dropout modes.
#[test]
fn centralized_smoother_equals_the_batch_estimator_with_own_starts() {
    let model = model_from(&format!("{}{OWN_STARTS}", crate::smoother::SMALL));
    crate::smoother::centralized_against_batch(&model, &simulate_run(&model, 5), 1e-10);
}

/// Without coupling each subsystem is filtered on its own: the joint filter with `k = 0` and
/// the distributed filter (which shares one covariance recursion between subsystems only
/// where they also start alike) agree from their different starts.
#[test]
fn decoupled_subsystems_are_filtered_from_their_own_starts() {
    let text = CHAIN
        .replace(
            "B = [[0.2, 0.1], [0.1, 0.3]]",
            "B = [[0.0, 0.0], [0.0, 0.0]]",
        )
        .replace("H = [[0.2], [-0.1]]", "H = [[0.0], [0.0]]")
        .replace("p = [0.9, 0.6, 0.8, 0.7]", "p = 0.8")
        .replace(
            "subsystems = [2, 3]\nsteps = [8, 15]",
            "subsystems = [1, 4]",
        )
        .replace(
            "G = [[0.1, 0.4], [-0.2, 0.2]]",
            "G = [[0.0, 0.0], [0.0, 0.0]]",
        )
        .replace(
            "G = [[0.3, -0.2], [0.25, 0.1]]",
            "G = [[0.0, 0.0], [0.0, 0.0]]",
        );
    let model = model_from(&format!("{text}{OWN_STARTS}"));
    let run = simulate_run(&model, 7);
    let mut joint = JointFilter::new(
        &model,
        JointOptions {
            band: 0,
            second_moment: SecondMoment::Local,
            ..JointOptions::default()
        },
    )
    .unwrap();
    let mut two = sisfilt::filter::TwoStepFilter::new(&model, Default::default()).unwrap();
    let mut gap: f64 = 0.0;
    for (y, u) in run.y.iter().zip(&run.u) {
        joint.step(y, u).unwrap();
        two.step(y, u).unwrap();
        let ((xa, pa), (xb, pb)) = (joint.filtered(), two.filtered());
        for (a, b) in xa.iter().chain(pa).zip(xb.iter().chain(pb)) {
            gap = gap.max((a - b).abs() / (1.0 + b.abs()));
        }
    }
    assert!(gap < 1e-10, "{gap:e}");
    // The starts matter: from the shared start the first step's estimates differ.
    let shared = model_from(&text);
    let mut from_shared = sisfilt::filter::TwoStepFilter::new(&shared, Default::default()).unwrap();
    let mut own = sisfilt::filter::TwoStepFilter::new(&model, Default::default()).unwrap();
    from_shared.step(&run.y[0], &run.u[0]).unwrap();
    own.step(&run.y[0], &run.u[0]).unwrap();
    assert!((own.filtered().0[2] - from_shared.filtered().0[2]).abs() > 1e-3);
}
