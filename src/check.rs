//! What `check` finds in a model, as a value (docs/theory.md §13): its dimensions, which
//! parameters vary in time or space, and per window of parameters the interconnection
//! system's condition, the spectral radius of the lifted `A_eff` (docs/theory.md §3), the
//! band of `A_eff` with the joint filter's cost (§8), and the memory of each smoother (§9).
//! A front end prints it, or hands it on (a Python dict).

use serde::Serialize;

use crate::error::Result;
use crate::filter::joint::{DEFAULT_BAND, DEFAULT_BAND_TOL, flops_per_subsystem_step};
use crate::interconnect::ChainSolver;
use crate::lifted::a_eff_band;
use crate::memory::DEFAULT_MAX_MEMORY;
use crate::model::{Dims, MATRIX_KEYS, Model};
use crate::smoother::{SmootherKind, memory_bytes};
use crate::stability::{RadiusEffort, SpectralRadius, Stability, spectral_radius};

/// The figures of a model.
#[derive(Debug, Clone, Serialize)]
pub struct ModelCheck {
    pub subsystems: usize,
    /// The config's `steps`, when it gives them.
    pub steps: Option<usize>,
    pub dims: Dims,
    /// The parameters (`A` … `Q`, then `p`) that vary, in that order.
    pub varying: Vec<Variation>,
    /// Every `Q` is zero (the paper's setting).
    pub q_is_zero: bool,
    /// One per window of parameters that starts by `T` (every one without `steps`), in time
    /// order.
    pub windows: Vec<WindowCheck>,
    /// The joint filter's default band `k` (at most `N − 1`), which the costs below assume.
    pub joint_band: usize,
    /// Bytes each smoother's stored forward pass takes for the `T` steps of the model (when
    /// the config gives `steps`).
    pub smoother_memory: Option<SmootherMemory>,
}

/// A parameter that varies, and how.
#[derive(Debug, Clone, Serialize)]
pub struct Variation {
    /// Its config key (`A`, …, `Q`, `p`, `initial`).
    pub key: &'static str,
    pub time: bool,
    pub space: bool,
}

/// The figures of the window of parameters in force over the steps `first..=last`.
#[derive(Debug, Clone, Serialize)]
pub struct WindowCheck {
    pub first: usize,
    /// The last step of the window: `None` for the last window of a config without `steps`,
    /// which has no end.
    pub last: Option<usize>,
    /// The interconnection system's condition estimate (1-norm).
    pub condition: f64,
    /// The spectral radius of `A_eff`: exact, or a Krylov estimate.
    pub spectral_radius: SpectralRadius,
    /// The half-width `b` of `A_eff`'s band at the default tolerance.
    pub a_eff_half_width: usize,
    /// That tolerance.
    pub band_tol: f64,
    /// The joint filter's flops per subsystem-step at the default band, with its band moment.
    pub joint_flops: f64,
    /// The subsystems without a sensor (1-based; an override's `measured = false`).
    pub unmeasured: Vec<usize>,
}

/// Bytes the stored forward pass of each smoother takes.
#[derive(Debug, Clone, Serialize)]
pub struct SmootherMemory {
    pub distributed: u64,
    /// At the default band.
    pub joint: u64,
    pub centralized: u64,
}

impl ModelCheck {
    /// The windows whose `A_eff` is not stable: a spectral radius of 1 within its bound, or
    /// above (docs/theory.md §3).
    pub fn unstable_windows(&self) -> impl Iterator<Item = &WindowCheck> {
        self.windows
            .iter()
            .filter(|w| w.spectral_radius.stability() != Stability::Stable)
    }
}

/// What a spectral radius of `A_eff` that is not below 1 means for the chain and the filters
/// (docs/theory.md §3), for a warning: 1 within its bound is a marginally stable chain whose
/// second moment grows like a power of `t`; above 1, exact, an unstable one whose moment grows
/// exponentially; above 1, estimated, one whose powers grow at least Kreiss's
/// `(ρ − 1) / bound`-fold.
pub fn instability(rho: &SpectralRadius) -> String {
    let (value, bound) = (rho.value, rho.bound);
    let marginal = "the chain is marginally stable: its second moment S grows like a power of t (linearly for a random walk), not exponentially, and the unknown-dropout filter's R_eff = M + p(1−p) J S Jᵀ with it, so its gain slowly fades";
    match (rho.stability(), rho.exact) {
        (Stability::Unstable, true) => format!(
            "the spectral radius of A_eff is {value:.6} > 1: the chain is unstable, its second moment grows exponentially, and the unknown-dropout filter diverges (docs/theory.md §3)"
        ),
        (Stability::Unstable, false) => format!(
            "the spectral radius of A_eff is estimated at {value:.6} ± {bound:.1e} (Krylov), above 1: the chain is unstable, or so far from normal that some power of A_eff grows at least {:.1}-fold (Kreiss's bound); either way the unknown-dropout filter's second moment grows with it (docs/theory.md §3); sisfilt check on a copy of the chain of at most {} lifted states (N·n) gives its exact radius",
            rho.least_growth(),
            RadiusEffort::DEFAULT.exact_max
        ),
        (_, true) => format!(
            "the spectral radius of A_eff is {value:.6} = 1 (to {bound:.1e}): {marginal} (docs/theory.md §3)"
        ),
        (_, false) => format!(
            "the spectral radius of A_eff is estimated at {value:.6} ± {bound:.1e} (Krylov), which does not exclude 1: no instability is shown, and if the radius is 1, {marginal} (docs/theory.md §3); sisfilt check on a copy of the chain of at most {} lifted states (N·n) gives its exact radius",
            RadiusEffort::DEFAULT.exact_max
        ),
    }
}

/// The figures of `model` (one chain solve and one spectral radius per window).
pub fn check(model: &Model) -> Result<ModelCheck> {
    let varying = MATRIX_KEYS
        .iter()
        .copied()
        .chain(["p"])
        .filter_map(|key| {
            let (time, space) = model.variation(key);
            (time || space).then_some(Variation { key, time, space })
        })
        .chain((!model.initial.shared()).then_some(Variation {
            key: "initial",
            time: false,
            space: true,
        }))
        .collect();
    let joint_band = DEFAULT_BAND.min(model.subsystems - 1);
    let all = model.windows();
    let mut windows: Vec<WindowCheck> = Vec::new();
    let horizon = model.steps.unwrap_or(usize::MAX);
    for (k, w) in all.iter().enumerate() {
        if w.first > horizon {
            break;
        }
        let last = all
            .get(k + 1)
            .map(|next| next.first - 1)
            .or(model.steps)
            .map(|last| last.min(horizon));
        let unmeasured = (1..=model.subsystems)
            .filter(|&i| !w.measured[i - 1])
            .collect();
        let figures = match model.first_window_of_chain(k) {
            earlier if earlier < k => windows[earlier].clone(),
            _ => window_figures(model, w.first, joint_band)?,
        };
        windows.push(WindowCheck {
            first: w.first,
            last,
            unmeasured,
            ..figures
        });
    }
    let memory = |steps| SmootherMemory {
        distributed: memory_bytes(model, SmootherKind::Distributed, steps),
        joint: memory_bytes(model, SmootherKind::Joint(joint_band), steps),
        centralized: memory_bytes(model, SmootherKind::Centralized, steps),
    };
    Ok(ModelCheck {
        subsystems: model.subsystems,
        steps: model.steps,
        dims: model.dims,
        varying,
        q_is_zero: model.q_is_zero(),
        windows,
        joint_band,
        smoother_memory: model.steps.map(memory),
    })
}

/// The figures of the chain in force at `t` (its `first`, `last` and `unmeasured` are the
/// caller's to set).
fn window_figures(model: &Model, t: usize, joint_band: usize) -> Result<WindowCheck> {
    let solver = ChainSolver::new(model, t)?;
    let b = a_eff_band(model, t, &solver, DEFAULT_BAND_TOL, DEFAULT_MAX_MEMORY)?.half_width();
    Ok(WindowCheck {
        first: t,
        last: None,
        condition: solver.condition(),
        spectral_radius: spectral_radius(model, t, &solver, RadiusEffort::DEFAULT),
        a_eff_half_width: b,
        band_tol: DEFAULT_BAND_TOL,
        unmeasured: Vec::new(),
        joint_flops: flops_per_subsystem_step(model.dims.n, joint_band, b, model.subsystems, true),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An uncoupled chain (`B = 0`): `A_eff = blkdiag(A)`, so each window's spectral radius is
    /// the largest `|A|` of its subsystems.
    #[test]
    fn each_window_has_the_radius_of_its_own_a() {
        let text = r#"
            subsystems = 3
            steps = 6
            [interconnection]
            plus = 1
            minus = 1
            [model]
            A = [[0.5]]
            B = [[0.0, 0.0]]
            D = [[0.0], [0.0]]
            G = [[0.0, 0.0], [0.0, 0.0]]
            J = [[1.0]]
            M = [[0.1]]
            [dropout]
            p = 0.9
            [initial]
            cov = [[1.0]]
            [[override]]
            subsystems = [2, 2]
            steps = [3, 4]
            A = [[-1.5]]
        "#;
        let model = Model::from_toml_str("chain.toml", std::path::Path::new("."), text).unwrap();
        let figures = check(&model).unwrap();
        let spans: Vec<(usize, Option<usize>, f64)> = figures
            .windows
            .iter()
            .map(|w| (w.first, w.last, w.spectral_radius.value))
            .collect();
        assert_eq!(spans.len(), 3, "{spans:?}");
        for ((first, last, rho), (want_first, want_last, want_rho)) in
            spans.iter().zip([(1, 2, 0.5), (3, 4, 1.5), (5, 6, 0.5)])
        {
            assert_eq!((*first, *last), (want_first, Some(want_last)));
            assert!((rho - want_rho).abs() < 1e-12, "{spans:?}");
        }
        let unstable: Vec<usize> = figures.unstable_windows().map(|w| w.first).collect();
        assert_eq!(unstable, [3]);
        assert_eq!(figures.varying.len(), 1);
        let a = &figures.varying[0];
        assert_eq!((a.key, a.time, a.space), ("A", true, true));
        assert!(figures.q_is_zero);
        assert_eq!(figures.joint_band, 2);
    }
}
