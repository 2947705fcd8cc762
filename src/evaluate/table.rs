//! The tables `evaluate` prints on standard output.

use super::{Evaluation, Sweep};
use crate::accuracy::AccuracyReport;
use crate::choice::Choice;

impl Sweep {
    /// The tables printed on standard output: overall RMSE and ANEES, one row per `p`.
    pub fn table(&self) -> String {
        let o = &self.options;
        let mut s = format!(
            "{}: {} × T = {} × N = {} per value of p; scored t > {}; p replaces the config's arrival probability at every (t, i)\n",
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
        let block = |title: &str,
                     pick: &dyn Fn(&AccuracyReport) -> Option<f64>,
                     format: &dyn Fn(f64) -> String| {
            let mut b = format!("\n{title}\n{:<8}", "p");
            for (n, w) in names.iter().zip(&widths) {
                b += &format!(" {n:>w$}");
            }
            b += "\n";
            for (p, e) in self.sweep_p.iter().zip(&self.evaluations) {
                b += &format!("{p:<8}");
                for (f, w) in e.filters.iter().zip(&widths) {
                    let cell = match &f.accuracy {
                        None => "-".to_string(),
                        Some(a) => pick(a).map_or("inf".into(), format),
                    };
                    b += &format!(" {cell:>w$}");
                }
                b += "\n";
            }
            b
        };
        s += &block("RMSE (overall)", &|a| Some(a.rmse_overall), &|v| {
            format!("{v:.4e}")
        });
        // As in the table of one evaluation.
        s += &block("ANEES", &|a| a.anees, &|v| figure(v));
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
        let mut s = format!(
            "{}: {} × T = {} × N = {}; scored t > {}\n\n",
            self.config,
            o.runs_and_seeds(),
            self.steps,
            self.subsystems,
            o.burn_in
        );
        let n = self
            .filters
            .iter()
            .find_map(|f| f.accuracy.as_ref())
            .map_or(0, |a| a.rmse.len());
        s += &format!("{:<20} {:>10}", "filter", "RMSE");
        for k in 1..=n {
            s += &format!(" {:>10}", format!("RMSE x{k}"));
        }
        s += &format!(
            " {:>9} {:>10} {:>17} {:>8} {:>9}\n",
            "/ central", "ANEES", "95 % band", "left out", "time (s)"
        );
        let mut notes = Vec::new();
        for f in &self.filters {
            match (&f.accuracy, &f.skipped) {
                (Some(a), _) => {
                    if !a.rmse_overall.is_finite() {
                        notes.push(format!(
                            "{}: its estimates overflowed (with --paper this is the transfer solver on a long chain, docs/theory.md §2)",
                            f.name
                        ));
                    }
                    s += &format!("{:<20} {:>10.4e}", f.name, a.rmse_overall);
                    for r in &a.rmse {
                        s += &format!(" {r:>10.4e}");
                    }
                    let ratio = f.rmse_ratio.map_or("-".into(), figure);
                    let anees = a.anees.map_or("inf".into(), figure);
                    s += &format!(
                        " {ratio:>9} {anees:>10} {:>17} {:>8} {:>9.2}\n",
                        format!("[{:.3}, {:.3}]", a.anees_band[0], a.anees_band[1]),
                        a.nees_left_out,
                        f.wall_time_s
                    );
                }
                (None, Some(why)) => {
                    s += &format!("{:<20} skipped (see note)\n", f.name);
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
            s += &format!("{:<20} {}\n", f.name, f.description);
        }
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
