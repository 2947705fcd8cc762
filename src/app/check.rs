//! `sisfilt check`: validates a config and reports its dimensions, which parameters vary,
//! the interconnection system's condition and the spectral radius of the lifted `A_eff`.

use std::path::Path;

use anyhow::Result;

use sisfilt::filter::joint::{DEFAULT_BAND, DEFAULT_BAND_TOL, flops_per_subsystem_step};
use sisfilt::inputs::InputStream;
use sisfilt::interconnect::ChainSolver;
use sisfilt::lifted::{a_eff_band, spectral_radius};
use sisfilt::messages::warn;
use sisfilt::model::{MATRIX_KEYS, Model};
use sisfilt::smoother::{DEFAULT_MAX_MEMORY, SmootherKind, human_bytes, memory_bytes};

use super::print_line;

/// Power-iteration steps for the spectral radius (`estimate` takes fewer: it only wants a
/// quick stability warning).
const POWER_STEPS: usize = 4000;

/// `sisfilt check CONFIG`: the report on standard output, warnings on standard error.
pub fn run(path: &Path) -> Result<()> {
    let model = Model::load(path)?;
    let d = model.dims;
    // Everything simulate reads: the inputs file too.
    let mut inputs = InputStream::open(&model, None)?;
    let mut u = vec![0.0; model.subsystems * d.m];
    for t in 1..=model.steps {
        inputs.next(t, &mut u)?;
    }
    inputs.finish(model.steps)?;

    let mut report: Vec<String> = Vec::new();
    let mut warnings: Vec<String> = Vec::new();
    report.push(format!("config: {}", path.display()));
    report.push(format!(
        "chain: N = {} subsystems, T = {} steps",
        model.subsystems, model.steps
    ));
    report.push(format!(
        "dimensions: n = {}, m = {}, q = {}, plus = {}, minus = {}",
        d.n, d.m, d.q, d.plus, d.minus
    ));
    let mut varying = Vec::new();
    for key in MATRIX_KEYS.iter().copied().chain(["p"]) {
        let (time, space) = model.variation(key);
        let how = match (time, space) {
            (true, true) => "time and space",
            (true, false) => "time",
            (false, true) => "space",
            (false, false) => continue,
        };
        varying.push(format!("{key} ({how})"));
    }
    report.push(format!(
        "varying parameters: {}",
        if varying.is_empty() {
            "none".to_string()
        } else {
            varying.join(", ")
        }
    ));
    report.push(format!(
        "process noise: {}",
        if model.q_is_zero() {
            "Q = 0 (the paper's setting)"
        } else {
            "Q > 0"
        }
    ));
    let windows = model.windows();
    for (k, w) in windows.iter().enumerate() {
        if w.first > model.steps {
            break;
        }
        let last = windows
            .get(k + 1)
            .map_or(model.steps, |n| (n.first - 1).min(model.steps));
        let solver = ChainSolver::new(&model, w.first)?;
        let rho = spectral_radius(&model, w.first, POWER_STEPS)?;
        let b = a_eff_band(&model, w.first, &solver, DEFAULT_BAND_TOL).half_width();
        let k = DEFAULT_BAND.min(model.subsystems - 1);
        let joint_line = format!(
            "t = {}..{}: A_eff band half-width b = {b} (tol {DEFAULT_BAND_TOL:e}); joint filter (--band {k}): about {:.1} kflop per subsystem-step",
            w.first,
            last,
            flops_per_subsystem_step(d.n, k, b, model.subsystems, true) / 1e3,
        );
        report.push(format!(
            "t = {}..{}: interconnection condition estimate {:.3e} (1-norm), spectral radius of A_eff {:.6} ({})",
            w.first,
            last,
            solver.condition(),
            rho.value,
            if rho.exact {
                "exact"
            } else {
                "power-iteration estimate"
            }
        ));
        report.push(joint_line);
        if rho.value >= 1.0 {
            warnings.push(format!(
                "t = {}..{last}: the spectral radius of A_eff is {:.6} ≥ 1: the chain is not stable, and the unknown-dropout filter diverges (docs/theory.md §3)",
                w.first, rho.value
            ));
        }
    }
    let k = DEFAULT_BAND.min(model.subsystems - 1);
    report.push(format!(
        "smoothing memory for T = {}: distributed {}, joint (--band {k}) {}, centralized {} (--max-memory, default {})",
        model.steps,
        human_bytes(memory_bytes(&model, SmootherKind::Distributed, model.steps)),
        human_bytes(memory_bytes(&model, SmootherKind::Joint(k), model.steps)),
        human_bytes(memory_bytes(&model, SmootherKind::Centralized, model.steps)),
        human_bytes(DEFAULT_MAX_MEMORY),
    ));
    // Print only once everything passed, so that a bad config prints nothing on stdout.
    print_line(&report.join("\n"))?;
    for w in warnings {
        warn(w);
    }
    Ok(())
}
