//! The tables `evaluate` prints on standard output.

use super::{Evaluation, FAILED, FilterResult, Sweep};
use crate::accuracy::{AccuracyReport, DetectionReport};
use crate::choice::Choice;

impl Sweep {
    /// The tables printed on standard output: overall RMSE and ANEES, one row per `p`.
    pub fn table(&self) -> String {
        let o = &self.options;
        let replaces = match o.true_p {
            None => "p replaces the config's arrival probability at every (t, i)".to_string(),
            Some(truth) => format!(
                "p replaces the filters' arrival probability at every (t, i); simulated with p = {truth}"
            ),
        };
        let mut s = format!(
            "{}: {} × T = {} × N = {} per value of p; scored t > {}; {replaces}\n",
            self.config,
            o.runs_and_seeds(),
            self.steps,
            self.subsystems,
            o.burn_in
        );
        let names: Vec<&str> = self.evaluations[0]
            .filters
            .iter()
            .map(|f| f.name.name())
            .collect();
        let widths: Vec<usize> = names.iter().map(|n| n.len().max(10) + 2).collect();
        let block = |title: &str, cell: &dyn Fn(&FilterResult) -> String| {
            let mut b = format!("\n{title}\n{:<8}", "p");
            for (n, w) in names.iter().zip(&widths) {
                b += &format!(" {n:>w$}");
            }
            b += "\n";
            for (p, e) in self.sweep_p.iter().zip(&self.evaluations) {
                b += &format!("{p:<8}");
                for (f, w) in e.filters.iter().zip(&widths) {
                    b += &format!(" {:>w$}", cell(f));
                }
                b += "\n";
            }
            b
        };
        let accuracy = |pick: fn(&AccuracyReport) -> Option<f64>, format: fn(f64) -> String| {
            move |f: &FilterResult| match &f.accuracy {
                None => "-".to_string(),
                Some(a) => pick(a).map_or("inf".into(), format),
            }
        };
        s += &block(
            "RMSE (overall)",
            &accuracy(|a| Some(a.rmse_overall), |v| format!("{v:.4e}")),
        );
        // As in the table of one evaluation.
        s += &block("ANEES", &accuracy(|a| a.anees, figure));
        let detects = |e: &Evaluation| e.filters.iter().any(|f| f.detection.is_some());
        if self.evaluations.iter().any(detects) {
            s += &block("lost measurements detected (π < 0.5)", &|f| {
                f.detection.map_or("-".into(), detected)
            });
        }
        let mut notes: Vec<String> = Vec::new();
        for (k, name) in names.iter().enumerate() {
            let skipped: Vec<String> = self
                .sweep_p
                .iter()
                .zip(&self.evaluations)
                .filter_map(|(p, e)| e.filters[k].skipped.as_ref().map(|w| (p, w)))
                .map(|(p, w)| format!("p = {p}: {w}"))
                .collect();
            if let Some(first) = skipped.first() {
                if skipped.len() == self.sweep_p.len() {
                    let why = first.split_once(": ").map_or(first.as_str(), |x| x.1);
                    notes.push(format!("note: {name}: skipped for every p: {why}"));
                } else {
                    notes.push(format!("note: {name}: {}", skipped.join("; ")));
                }
            }
        }
        if !notes.is_empty() {
            s += "\n";
            for n in notes {
                s += &n;
                s += "\n";
            }
        }
        s
    }
}

impl Evaluation {
    /// The table printed on standard output.
    pub fn table(&self) -> String {
        let o = &self.options;
        let truth = o.true_p.map_or(String::new(), |p| {
            format!("; simulated with p = {p} at every (t, i), the filters assume the config's p")
        });
        let mut s = format!(
            "{}: {} × T = {} × N = {}; scored t > {}{truth}\n\n",
            self.config,
            o.runs_and_seeds(),
            self.steps,
            self.subsystems,
            o.burn_in
        );
        let detects = self.filters.iter().any(|f| f.detection.is_some());
        let w = self
            .filters
            .iter()
            .map(|f| f.name.name().len())
            .fold(20, usize::max);
        let n = self
            .filters
            .iter()
            .find_map(|f| f.accuracy.as_ref())
            .map_or(0, |a| a.rmse.len());
        s += &format!("{:<w$} {:>10}", "filter", "RMSE");
        for k in 1..=n {
            s += &format!(" {:>10}", format!("RMSE x{k}"));
        }
        s += &format!(
            " {:>9} {:>10} {:>17} {:>8} {:>9}",
            "/ central", "ANEES", "95 % band", "left out", "time (s)"
        );
        if detects {
            s += &format!(" {:>8} {:>9} {:>12}", "|π − γ|", "detected", "false alarms");
        }
        s += "\n";
        let mut notes = Vec::new();
        for f in &self.filters {
            match (&f.accuracy, &f.skipped) {
                (Some(a), _) => {
                    if !a.rmse_overall.is_finite() {
                        notes.push(format!(
                            "{}: its estimates overflowed (for the paper's filter: its transfer solver loses accuracy exponentially along a long chain, docs/theory.md §2)",
                            f.name
                        ));
                    }
                    s += &format!("{:<w$} {:>10.4e}", f.name, a.rmse_overall);
                    for r in &a.rmse {
                        s += &format!(" {r:>10.4e}");
                    }
                    let ratio = f.rmse_ratio.map_or("-".into(), figure);
                    let anees = a.anees.map_or("inf".into(), figure);
                    s += &format!(
                        " {ratio:>9} {anees:>10} {:>17} {:>8} {:>9.2}",
                        format!("[{:.3}, {:.3}]", a.anees_band[0], a.anees_band[1]),
                        a.nees_left_out,
                        f.wall_time_s
                    );
                    match (&f.detection, detects) {
                        (Some(d), _) => {
                            s += &format!(
                                " {:>8.4} {:>9} {:>12}",
                                d.mean_abs_error,
                                detected(*d),
                                format!("{:.2} %", d.false_alarm_percent())
                            );
                        }
                        (None, true) => s += &format!(" {:>8} {:>9} {:>12}", "-", "-", "-"),
                        (None, false) => {}
                    }
                    s += "\n";
                }
                (None, Some(why)) => {
                    let what = if why.starts_with(FAILED) {
                        "failed"
                    } else {
                        "skipped"
                    };
                    s += &format!("{:<w$} {what} (see note)\n", f.name);
                    notes.push(format!("{}: {why}", f.name));
                }
                (None, None) => {}
            }
        }
        s += "\n";
        let smoother_ratios: Vec<String> = self
            .filters
            .iter()
            .filter_map(|f| f.rmse_ratio_to_filter.map(|r| format!("{} {r:.4}", f.name)))
            .collect();
        if !smoother_ratios.is_empty() {
            s += &format!(
                "smoothers: \"/ central\" is to centralized-smoother; RMSE / centralized filter: {}\n\n",
                smoother_ratios.join(", ")
            );
        }
        for f in &self.filters {
            s += &format!("{:<w$} {}\n", f.name, f.description);
        }
        s += &format!(
            "{:<w$} of a consistent filter's ANEES: 1 ± t·s/√R from the spread s of the R runs' own ANEES (the terms of one run are correlated; the runs are independent)\n",
            "95 % band"
        );
        for note in notes {
            s += &format!("note: {note}\n");
        }
        s
    }
}

/// A ratio or an ANEES in the tables: four decimals, or three significant digits once it
/// reaches 10⁴ (a diverging filter's figures would fill the line).
fn figure(v: f64) -> String {
    if v < 1e4 {
        format!("{v:.4}")
    } else {
        format!("{v:.3e}")
    }
}

/// The share of lost measurements detected, or `none lost` (at `p = 1`).
fn detected(d: DetectionReport) -> String {
    if d.lost == 0 {
        "none lost".into()
    } else {
        format!("{:.1} %", d.detected_percent())
    }
}
