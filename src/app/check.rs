//! `sisfilt check`: validates a config and reports its dimensions, which parameters vary,
//! the interconnection system's condition and the spectral radius of the lifted `A_eff`
//! ([`sisfilt::check::ModelCheck`], printed).

use std::path::Path;

use anyhow::Result;

use sisfilt::check::{ModelCheck, WindowCheck, check, instability};
use sisfilt::config::ConfigSetting;
use sisfilt::inputs::InputStream;
use sisfilt::memory::{DEFAULT_MAX_MEMORY, human_bytes};
use sisfilt::messages::warn;
use sisfilt::model::Model;

use super::print_line;

/// `sisfilt check CONFIG`: the report on standard output, warnings on standard error.
pub fn run(path: &Path, settings: &[ConfigSetting]) -> Result<()> {
    let model = Model::load(path, settings)?;
    // Everything simulate reads: the inputs file too (all of it without `steps`). Generated
    // inputs hold nothing to check, so a `steps` far beyond any file costs nothing; a file's
    // rows end at its size.
    if InputStream::path(&model, None).is_some() {
        let mut inputs = InputStream::open(&model, None)?;
        let mut u = vec![0.0; model.subsystems * model.dims.m];
        match model.steps {
            Some(steps) => {
                for t in 1..=steps {
                    inputs.next(t, &mut u)?;
                }
                inputs.finish(steps)?;
            }
            None => inputs.read_to_end()?,
        }
    }
    let figures = check(&model)?;
    // Print only once everything passed, so that a bad config prints nothing on stdout.
    print_line(&report(path, settings, &figures))?;
    // With p = 1 everywhere no filter weighs the second moment that an unstable chain grows.
    for w in figures
        .unstable_windows()
        .filter(|_| model.loses_readings())
    {
        warn(format!("{}: {}", span(w), instability(&w.spectral_radius)));
    }
    Ok(())
}

/// The report of `check` on the config at `path`, a line per figure.
fn report(path: &Path, settings: &[ConfigSetting], figures: &ModelCheck) -> String {
    let d = figures.dims;
    let set: String = settings.iter().map(|s| format!(" --set {s}")).collect();
    let mut report = vec![
        format!("config: {}{set}", path.display()),
        match figures.steps {
            Some(steps) => format!(
                "chain: N = {} subsystems, T = {steps} steps",
                figures.subsystems
            ),
            None => format!(
                "chain: N = {} subsystems, T not set (estimate takes it from its data; simulate needs steps or --steps)",
                figures.subsystems
            ),
        },
        format!(
            "dimensions: n = {}, m = {}, q = {}, plus = {}, minus = {}",
            d.n, d.m, d.q, d.plus, d.minus
        ),
    ];
    let varying: Vec<String> = figures
        .varying
        .iter()
        .map(|v| {
            let how = match (v.time, v.space) {
                (true, true) => "time and space",
                (true, false) => "time",
                _ => "space",
            };
            format!("{} ({how})", v.key)
        })
        .collect();
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
        if figures.q_is_zero {
            "Q = 0 (the paper's setting)"
        } else {
            "Q > 0"
        }
    ));
    let k = figures.joint_band;
    for w in &figures.windows {
        report.push(format!(
            "{}: interconnection condition estimate {:.3e} (1-norm), spectral radius of A_eff {:.6} ({})",
            span(w),
            w.condition,
            w.spectral_radius.value,
            if w.spectral_radius.exact {
                format!("exact to {:.1e}", w.spectral_radius.bound)
            } else {
                format!("Krylov estimate ± {:.1e}", w.spectral_radius.bound)
            }
        ));
        report.push(format!(
            "{}: A_eff band half-width b = {} (tol {:e}); joint filter (--band {k}): about {:.1} kflop per subsystem-step",
            span(w),
            w.a_eff_half_width,
            w.band_tol,
            w.joint_flops / 1e3,
        ));
        if !w.unmeasured.is_empty() {
            let list: Vec<String> = w.unmeasured.iter().map(ToString::to_string).collect();
            report.push(format!(
                "{}: no sensor on subsystems {} (their measurements are gaps)",
                span(w),
                list.join(", ")
            ));
        }
    }
    if let (Some(memory), Some(steps)) = (&figures.smoother_memory, figures.steps) {
        report.push(format!(
            "smoothing memory for T = {steps}: distributed {}, joint (--band {k}) {}, centralized {} (--max-memory, default {})",
            human_bytes(memory.distributed),
            human_bytes(memory.joint),
            human_bytes(memory.centralized),
            human_bytes(DEFAULT_MAX_MEMORY),
        ));
    }
    report.join("\n")
}

/// `t = first..last` of a window, `t ≥ first` for one without end.
fn span(w: &WindowCheck) -> String {
    match w.last {
        Some(last) => format!("t = {}..{last}", w.first),
        None => format!("t ≥ {}", w.first),
    }
}
