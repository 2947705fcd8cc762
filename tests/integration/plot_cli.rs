//! `sisfilt plot`, `completions`, `man`, `evaluate --sweep-p` and the `--quiet` / `--verbose`
//! flags from the command line. The figures are checked as SVG documents (parsed with
//! roxmltree): their texts, legends and the number of marks, against figures computed here from
//! the CSV and JSON files themselves; the same input must give the same bytes.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use crate::common::{Csv, one_error_line, shipped_config, sisfilt};

/// Runs `sisfilt` with `args` in `dir` and asserts success.
fn run_ok(dir: &Path, args: &[&str]) -> assert_cmd::assert::Assert {
    sisfilt().current_dir(dir).args(args).assert().success()
}

/// The data every test draws from, made once per test binary: simulations of the platoon
/// (J = I, so y1 measures x1) and of the paper's chain (J = [1 0.5]), their estimates (and the
/// centralized filter's, as a second estimate), and an evaluation of each.
fn fixture() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("plot_cli");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        for (name, out) in [("platoon.toml", "platoon"), ("paper.toml", "paper")] {
            let cfg = shipped_config(name);
            let cfg = cfg.to_str().unwrap();
            run_ok(&dir, &["simulate", cfg, "--out", out]);
            let meas = format!("{out}/measurements.csv");
            run_ok(
                &dir,
                &[
                    "-q",
                    "estimate",
                    "--meas",
                    &meas,
                    "--out",
                    &format!("{out}/estimates.csv"),
                ],
            );
            run_ok(
                &dir,
                &[
                    "-q",
                    "estimate",
                    "--meas",
                    &meas,
                    "--filter",
                    "centralized",
                    "--out",
                    &format!("{out}/central.csv"),
                ],
            );
            run_ok(
                &dir,
                &[
                    "-q",
                    "evaluate",
                    cfg,
                    "--runs",
                    "5",
                    "--out",
                    &format!("{out}/eval.json"),
                ],
            );
        }
        dir
    })
}

/// A plot command run in the fixture folder; returns the SVG text.
fn plot(args: &[&str], out: &str) -> String {
    let dir = fixture();
    let mut all = vec!["plot"];
    all.extend_from_slice(args);
    all.extend_from_slice(&["--out", out]);
    let assert = run_ok(dir, &all);
    assert!(
        assert.get_output().stdout.is_empty(),
        "plot writes nothing on standard output"
    );
    std::fs::read_to_string(dir.join(out)).unwrap()
}

/// The texts of an SVG document, one per `<text>` element (checks that it parses).
fn texts(svg: &str) -> Vec<String> {
    let doc = roxmltree::Document::parse(svg).expect("the SVG parses as XML");
    assert_eq!(doc.root_element().tag_name().name(), "svg");
    doc.descendants()
        .filter(|n| n.has_tag_name("text"))
        .map(|n| n.text().unwrap_or_default().trim().to_string())
        .collect()
}

/// How many elements `tag` the SVG holds with `attr = value`.
fn count(svg: &str, tag: &str, attr: &str, value: &str) -> usize {
    let doc = roxmltree::Document::parse(svg).unwrap();
    doc.descendants()
        .filter(|n| n.has_tag_name(tag) && n.attribute(attr) == Some(value))
        .count()
}

fn assert_has(texts: &[String], wanted: &str) {
    assert!(
        texts.iter().any(|t| t == wanted),
        "no text `{wanted}` in the figure; texts: {texts:#?}"
    );
}

fn assert_has_part(texts: &[String], wanted: &str) {
    assert!(
        texts.iter().any(|t| t.contains(wanted)),
        "no text containing `{wanted}` in the figure; texts: {texts:#?}"
    );
}

/// A column of a CSV by name, for the rows of subsystem `i`.
fn column(csv: &Csv, name: &str, i: usize) -> Vec<f64> {
    let c = csv.header.iter().position(|h| h == name).unwrap();
    csv.rows
        .iter()
        .filter(|r| r[1] == i.to_string())
        .map(|r| r[c].parse().unwrap())
        .collect()
}

#[test]
fn series_shows_truth_estimates_bands_measurements_and_losses() {
    let dir = fixture();
    let (i, k) = (5, 2);
    let svg = plot(
        &[
            "series",
            "--estimates",
            "platoon/estimates.csv",
            "--smoothed",
            "platoon/central.csv",
            "--truth",
            "platoon/truth.csv",
            "--meas",
            "platoon/measurements.csv",
            "--subsystem",
            "5",
            "--state",
            "2",
        ],
        "series.svg",
    );
    let t = texts(&svg);
    for label in [
        "truth",
        "estimates.csv ± 2σ",
        "central.csv ± 2σ",
        "measurement y2",
        "y when lost (noise only)",
        "time step t",
        "x2",
        "x̂2 − x2",
    ] {
        assert_has(&t, label);
    }

    // The lost steps, counted from the truth file: named in both legends, one tick each per
    // panel (plus the legend swatches), and the arrived measurements one dot each.
    let truth = Csv::read(&dir.join("platoon/truth.csv"));
    let gamma = column(&truth, "gamma", i);
    let lost = gamma.iter().filter(|g| **g == 0.0).count();
    assert!(lost > 5, "the platoon loses about 15 % of its measurements");
    let lost_text = format!("measurement lost (γ = 0): {lost} of {} steps", gamma.len());
    assert_eq!(t.iter().filter(|s| **s == lost_text).count(), 2, "{t:#?}");
    assert_eq!(
        count(&svg, "polyline", "stroke", "#D62728"),
        2 * lost + 2,
        "one lost-measurement tick per lost step and panel"
    );
    let arrived_dots = count(&svg, "circle", "fill", "#2CA02C");
    assert_eq!(
        arrived_dots,
        gamma.len() - lost + 1,
        "dots: arrived y + legend"
    );

    // The share of errors inside ±2σ, computed here from the files by column name.
    let est = Csv::read(&dir.join("platoon/estimates.csv"));
    let x_true = column(&truth, &format!("x{k}"), i);
    let x_hat = column(&est, &format!("x{k}"), i);
    let var = column(&est, &format!("P{k}_{k}"), i);
    let inside = (0..x_true.len())
        .filter(|&s| (x_hat[s] - x_true[s]).abs() <= 2.0 * var[s].sqrt())
        .count();
    let share = 100.0 * inside as f64 / x_true.len() as f64;
    assert_has(
        &t,
        &format!("error of estimates.csv, its ±2σ: {share:.1} % inside (95 % if honest)"),
    );

    // Deterministic: the same input gives the same bytes.
    let again = plot(
        &[
            "series",
            "--estimates",
            "platoon/estimates.csv",
            "--smoothed",
            "platoon/central.csv",
            "--truth",
            "platoon/truth.csv",
            "--meas",
            "platoon/measurements.csv",
            "--subsystem",
            "5",
            "--state",
            "2",
        ],
        "series-again.svg",
    );
    assert_eq!(svg, again);
}

#[test]
fn series_puts_measurements_of_a_mixed_j_in_their_own_panel() {
    // paper.toml measures y = x1 + 0.5 x2: no row of J picks x2 alone.
    let svg = plot(
        &[
            "series",
            "--estimates",
            "paper/estimates.csv",
            "--truth",
            "paper/truth.csv",
            "--meas",
            "paper/measurements.csv",
            "--subsystem",
            "3",
            "--state",
            "2",
        ],
        "series-paper.svg",
    );
    let t = texts(&svg);
    assert_has(&t, "Measurements y = γ J x + R u + d of subsystem 3");
    assert_has(&t, "Not drawn over x2: no row of J measures x2 alone.");
    assert_has(&t, "y1");
    // Without --meas there is no measurement panel and no measurement legend.
    let svg = plot(
        &[
            "series",
            "--estimates",
            "paper/estimates.csv",
            "--truth",
            "paper/truth.csv",
            "--subsystem",
            "3",
            "--state",
            "2",
        ],
        "series-paper-nomeas.svg",
    );
    let t = texts(&svg);
    assert!(!t.iter().any(|s| s.starts_with("Measurements")), "{t:#?}");
    assert_has(&t, "estimates.csv ± 2σ");
}

#[test]
fn series_reads_the_json_estimates_like_the_csv() {
    let dir = fixture();
    run_ok(
        dir,
        &[
            "-q",
            "estimate",
            "--meas",
            "paper/measurements.csv",
            "--out",
            "paper/estimate.json",
        ],
    );
    let args = |est: &'static str| {
        [
            "series",
            "--estimates",
            est,
            "--truth",
            "paper/truth.csv",
            "--subsystem",
            "2",
            "--state",
            "1",
        ]
    };
    let csv = plot(&args("paper/estimates.csv"), "from-csv.svg");
    let json = plot(&args("paper/estimate.json"), "from-json.svg");
    // Identical but for the file name in title and legend (of the same length, so that the
    // legend's layout is the same).
    assert_eq!(
        csv.replace("estimates.csv", "E"),
        json.replace("estimate.json", "E")
    );
}

/// The joint filter with the mixture update (and `extra` options) on the measurements of the
/// fixture's `run`, written to each of `outs` (a CSV and a JSON file).
fn joint_mixture_estimates(run: &str, extra: &[&str], outs: [&str; 2]) {
    let meas = format!("{run}/measurements.csv");
    for out in outs {
        let mut args = vec!["-q", "estimate", "--meas", &meas, "--filter", "joint"];
        args.extend_from_slice(&["--update", "mixture", "--out", out]);
        args.extend_from_slice(extra);
        run_ok(fixture(), &args);
    }
}

/// Estimates of the joint filter with the mixture update carry cross-covariance columns (in
/// JSON) and a last column `arrival`: the figures read them, and draw the same from the CSV
/// and the JSON.
#[test]
fn plots_read_the_joint_mixture_estimates() {
    joint_mixture_estimates("paper", &[], ["paper/mixture.csv", "paper/mixtur.json"]);
    for figure in ["series", "heatmap"] {
        let args = |est: &'static str| {
            let mut args = vec![figure, "--estimates", est, "--truth", "paper/truth.csv"];
            if figure == "series" {
                args.extend_from_slice(&["--subsystem", "2"]);
            }
            args.extend_from_slice(&["--state", "1"]);
            args
        };
        let csv = plot(&args("paper/mixture.csv"), &format!("{figure}-csv.svg"));
        let json = plot(&args("paper/mixtur.json"), &format!("{figure}-json.svg"));
        // Identical but for the file name (of the same length, for the same layout).
        assert!(
            csv.replace("mixture.csv", "E") == json.replace("mixtur.json", "E"),
            "{figure}"
        );
    }
}

/// With the mixture update's `arrival` column, each measurement is coloured by `π`: taken
/// (`π ≥ 0.9`, the measurement colour), weighed (amber) or set aside (`π ≤ 0.1`, red), its
/// shape still a dot where it arrived. The legend's counts and the dots of each colour are
/// recomputed here from the estimates' `arrival` column and the truth's `gamma`.
#[test]
fn series_colours_each_measurement_by_its_arrival_probability() {
    let dir = fixture();
    let i = 5;
    run_ok(
        dir,
        &[
            "-q",
            "estimate",
            "--meas",
            "platoon/measurements.csv",
            "--update",
            "mixture",
            "--out",
            "platoon/mixture.csv",
        ],
    );
    let svg = plot(
        &[
            "series",
            "--estimates",
            "platoon/mixture.csv",
            "--truth",
            "platoon/truth.csv",
            "--meas",
            "platoon/measurements.csv",
            "--subsystem",
            "5",
            "--state",
            "2",
        ],
        "series-mixture.svg",
    );
    let t = texts(&svg);
    let pi = column(&Csv::read(&dir.join("platoon/mixture.csv")), "arrival", i);
    let gamma = column(&Csv::read(&dir.join("platoon/truth.csv")), "gamma", i);
    let class = |s: usize| match pi[s] {
        p if p <= 0.1 => 0,
        p if p < 0.9 => 1,
        _ => 2,
    };
    let steps = |c: usize| (0..pi.len()).filter(|&s| class(s) == c).count();
    let dots = |c: usize| {
        (0..pi.len())
            .filter(|&s| class(s) == c && gamma[s] == 1.0)
            .count()
    };
    assert_has(
        &t,
        &format!("taken by the filter (π ≥ 0.9): {} steps", steps(2)),
    );
    assert_has(&t, &format!("weighed (0.1 < π < 0.9): {}", steps(1)));
    assert_has(&t, &format!("set aside as lost (π ≤ 0.1): {}", steps(0)));
    assert_has(&t, "measurement y2 (● arrived, × lost: noise only)");
    // The platoon sets aside some lost readings and takes most received ones.
    assert!(steps(0) > 0 && steps(2) > pi.len() / 2, "{pi:?}");
    for (c, fill) in [(0, "#D62728"), (1, "#F0AA00"), (2, "#2CA02C")] {
        assert_eq!(count(&svg, "circle", "fill", fill), dots(c), "{fill}");
    }
}

/// The heatmap's cell rectangles: every `rect` but the white background, the colour bar's 120
/// slices and its frame.
fn cell_count(svg: &str) -> usize {
    let doc = roxmltree::Document::parse(svg).unwrap();
    let rects = doc.descendants().filter(|n| n.has_tag_name("rect")).count();
    rects - 1 - 120 - 1
}

#[test]
fn heatmap_maps_every_cell_with_a_colour_bar() {
    let dir = fixture();
    let svg = plot(
        &[
            "heatmap",
            "--estimates",
            "platoon/estimates.csv",
            "--truth",
            "platoon/truth.csv",
        ],
        "heat.svg",
    );
    let t = texts(&svg);
    assert_has(&t, "time step t");
    assert_has(&t, "subsystem i");
    assert_has(&t, "|x̂1 − x1| / σ1");
    assert_has_part(&t, "each cell: one (t, i)");
    // N = 20 subsystems × T = 200 steps, one cell each.
    assert_eq!(cell_count(&svg), 20 * 200);
    // A consistent filter's normalised errors: the linear scale 0..3 (or a little more).
    assert_has(&t, "0");
    assert_has(&t, "3");
    assert!(!t.iter().any(|s| s == "(log scale)"));

    // --plain: the plain error, whose colour scale tops out at the 99th percentile of |x̂ − x|
    // rounded up to 1, 2, 2.5 or 5 × 10^j, computed here.
    let svg = plot(
        &[
            "heatmap",
            "--estimates",
            "platoon/estimates.csv",
            "--truth",
            "platoon/truth.csv",
            "--state",
            "2",
            "--plain",
        ],
        "heat-plain.svg",
    );
    let t = texts(&svg);
    assert_has(&t, "|x̂2 − x2|");
    let truth = Csv::read(&dir.join("platoon/truth.csv"));
    let est = Csv::read(&dir.join("platoon/estimates.csv"));
    let mut errors: Vec<f64> = (1..=20)
        .flat_map(|i| {
            let x = column(&truth, "x2", i);
            let xh = column(&est, "x2", i);
            (0..x.len())
                .map(|s| (xh[s] - x[s]).abs())
                .collect::<Vec<_>>()
        })
        .collect();
    errors.sort_by(f64::total_cmp);
    let p99 = errors[((errors.len() - 1) as f64 * 0.99).round() as usize];
    // The colour bar's tick labels are the only left-anchored numbers.
    let doc = roxmltree::Document::parse(&svg).unwrap();
    let ticks: Vec<f64> = doc
        .descendants()
        .filter(|n| n.has_tag_name("text") && n.attribute("text-anchor") == Some("start"))
        .filter_map(|n| n.text()?.trim().parse().ok())
        .collect();
    let top = ticks.iter().copied().fold(0.0, f64::max);
    assert!(ticks.len() >= 3, "{ticks:?}");
    assert!(
        top >= p99 && top <= 2.5 * p99,
        "colour bar top {top}, p99 {p99}"
    );
}

#[test]
fn heatmap_of_an_overconfident_filter_uses_decades() {
    // paper.toml has Q = 0: the two-step filter's σ shrinks to nothing while its error does
    // not, so |x̂ − x| / σ spans orders of magnitude (docs/theory.md §4).
    let svg = plot(
        &[
            "heatmap",
            "--estimates",
            "paper/estimates.csv",
            "--truth",
            "paper/truth.csv",
            "--state",
            "2",
        ],
        "heat-paper.svg",
    );
    let t = texts(&svg);
    assert_has(&t, "(log scale)");
    assert_has(&t, "1");
    assert_has(&t, "10");
    assert_eq!(cell_count(&svg), 6 * 150);
}

fn eval_json(dir: &Path, name: &str) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join(name)).unwrap()).unwrap()
}

/// Four significant digits, as the figure prints a value beside its bar or dot.
fn four_digits(v: f64) -> String {
    let decimals = (3 - v.abs().log10().floor() as i32).max(0) as usize;
    format!("{v:.decimals$}")
}

#[test]
fn evaluate_plot_shows_rmse_and_anees_of_each_filter() {
    let dir = fixture();
    for (input, out, log) in [
        ("platoon/eval.json", "eval-platoon.svg", false),
        ("paper/eval.json", "eval-paper.svg", true),
    ] {
        let svg = plot(&["evaluate", "--input", input], out);
        let t = texts(&svg);
        let json = eval_json(dir, input);
        for f in json["filters"].as_array().unwrap() {
            let name = f["name"].as_str().unwrap();
            // The name labels its RMSE bars and its ANEES dot, and its curve of the average
            // NEES per step when the evaluation carries one.
            let curve = f["nees_per_step"]
                .as_array()
                .is_some_and(|v| v.iter().any(|x| x.is_number()));
            let expected = 2 + usize::from(curve);
            assert_eq!(
                t.iter().filter(|s| *s == name).count(),
                expected,
                "{name}: {t:#?}"
            );
            match f["accuracy"].as_object() {
                Some(a) => {
                    let rmse = a["rmse_overall"].as_f64().unwrap();
                    assert_has(&t, &four_digits(rmse));
                    for r in a["rmse"].as_array().unwrap() {
                        assert_has(&t, &four_digits(r.as_f64().unwrap()));
                    }
                    assert_has(&t, &four_digits(a["anees"].as_f64().unwrap()));
                }
                None => assert_has_part(&t, "skipped: "),
            }
        }
        assert_has(&t, "overall");
        assert_has(&t, "x1");
        assert_has(&t, "x2");
        // The two-step filter's ANEES on paper.toml is in the thousands: a log scale.
        let desc = if log {
            "average NEES (log scale)"
        } else {
            "average NEES"
        };
        assert_has(&t, desc);
        // `evaluate` writes the average NEES per step: its panel is there.
        assert_has(&t, "Average NEES at each time step");
        let again = plot(&["evaluate", "--input", input], "again.svg");
        assert_eq!(svg, again, "same input, same bytes");
    }
}

#[test]
fn evaluate_plot_draws_nees_per_step_when_the_json_has_it() {
    let dir = fixture();
    let mut json = eval_json(dir, "platoon/eval.json");
    let steps = json["steps"].as_u64().unwrap() as usize;
    for (k, f) in json["filters"]
        .as_array_mut()
        .unwrap()
        .iter_mut()
        .enumerate()
    {
        let per_step: Vec<serde_json::Value> = (0..steps)
            .map(|t| {
                if t == 0 {
                    serde_json::Value::Null
                } else {
                    serde_json::json!(1.0 + 0.1 * k as f64 + 1e-3 * t as f64)
                }
            })
            .collect();
        f["nees_per_step"] = serde_json::Value::Array(per_step);
    }
    std::fs::write(
        dir.join("eval-steps.json"),
        serde_json::to_string(&json).unwrap(),
    )
    .unwrap();
    let svg = plot(
        &["evaluate", "--input", "eval-steps.json"],
        "eval-steps.svg",
    );
    let t = texts(&svg);
    assert_has(&t, "Average NEES at each time step");
    assert_has(&t, "average NEES (log scale)");
    assert_has(&t, "1 = honest covariance");
    // One curve per filter with figures (the skipped one has an array too, and is drawn).
    let curves = json["filters"].as_array().unwrap().len();
    let doc = roxmltree::Document::parse(&svg).unwrap();
    let long_lines = doc
        .descendants()
        .filter(|n| {
            n.has_tag_name("polyline")
                && n.attribute("points")
                    .is_some_and(|p| p.split(' ').count() >= steps - 1)
        })
        .count();
    assert_eq!(long_lines, curves);
}

#[test]
fn sweep_p_replaces_p_everywhere_and_plots_curves() {
    let dir = fixture();
    let cfg = shipped_config("paper.toml");
    let cfg = cfg.to_str().unwrap();
    let out = run_ok(
        dir,
        &[
            "-q",
            "evaluate",
            cfg,
            "--runs",
            "3",
            "--sweep-p",
            "0.5,0.8,1",
            "--out",
            "sweep.json",
        ],
    );
    let table = String::from_utf8(out.get_output().stdout.clone()).unwrap();
    assert!(
        table.contains("RMSE (overall)") && table.contains("ANEES"),
        "{table}"
    );
    let sweep = eval_json(dir, "sweep.json");
    assert_eq!(sweep["sweep_p"], serde_json::json!([0.5, 0.8, 1.0]));
    let evals = sweep["evaluations"].as_array().unwrap();
    assert_eq!(evals.len(), 3);

    // p = 0.8 is paper.toml's own p: the same figures as a plain evaluation.
    run_ok(
        dir,
        &[
            "-q",
            "evaluate",
            cfg,
            "--runs",
            "3",
            "--out",
            "plain-0.8.json",
        ],
    );
    let plain = eval_json(dir, "plain-0.8.json");
    for (a, b) in evals[1]["filters"]
        .as_array()
        .unwrap()
        .iter()
        .zip(plain["filters"].as_array().unwrap())
    {
        assert_eq!(a["accuracy"], b["accuracy"], "{}", a["name"]);
    }
    // At p = 1 nothing is lost: the Nahi filter's measurement model (H = pJ, R = M +
    // p(1 − p) J S Jᵀ) is the Kalman filter's, so the centralized filter equals the one that
    // knows the dropouts, and the naive filter the distributed one.
    let rmse = |name: &str| {
        evals[2]["filters"]
            .as_array()
            .unwrap()
            .iter()
            .find(|f| f["name"] == name)
            .unwrap()["accuracy"]["rmse_overall"]
            .as_f64()
            .unwrap()
    };
    let rel = |a: f64, b: f64| (a - b).abs() / b;
    assert!(rel(rmse("centralized"), rmse("centralized-known")) < 1e-9);
    assert!(rel(rmse("naive"), rmse("distributed")) < 1e-9);
    // At p = 0.5 they differ.
    let rmse_half = |name: &str| {
        evals[0]["filters"]
            .as_array()
            .unwrap()
            .iter()
            .find(|f| f["name"] == name)
            .unwrap()["accuracy"]["rmse_overall"]
            .as_f64()
            .unwrap()
    };
    assert!(rel(rmse_half("centralized"), rmse_half("centralized-known")) > 1e-3);

    let svg = plot(&["evaluate", "--input", "sweep.json"], "sweep.svg");
    let t = texts(&svg);
    assert_has(&t, "Accuracy against the arrival probability p");
    assert_has(&t, "arrival probability p");
    assert_has(&t, "average NEES (log scale)");
    for name in ["distributed", "centralized", "centralized-known", "naive"] {
        assert_eq!(t.iter().filter(|s| *s == name).count(), 2, "{name}");
    }
    // One curve of three points per filter that ran, in each panel: a dot each.
    let ran = evals[0]["filters"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| f["accuracy"].is_object())
        .count();
    let dots = roxmltree::Document::parse(&svg)
        .unwrap()
        .descendants()
        .filter(|n| n.has_tag_name("circle") && n.attribute("r") == Some("4"))
        .count();
    assert_eq!(dots, 2 * ran * 3);

    // Probabilities outside [0, 1] are bad input, named.
    let out = sisfilt()
        .current_dir(dir)
        .args(["evaluate", cfg, "--runs", "1", "--sweep-p", "0.5,1.5"])
        .assert()
        .code(2);
    let line = one_error_line(&out.get_output().stderr);
    assert!(line.contains("--sweep-p") && line.contains("1.5"), "{line}");
}

/// Runs a failing plot command and returns its one error line, asserting exit code 2.
fn plot_error(args: &[&str]) -> String {
    let mut all = vec!["plot"];
    all.extend_from_slice(args);
    all.extend_from_slice(&["--out", "bad.svg"]);
    let out = sisfilt().current_dir(fixture()).args(&all).assert().code(2);
    assert!(!fixture().join("bad.svg").exists(), "no output on failure");
    one_error_line(&out.get_output().stderr)
}

#[test]
fn bad_plot_input_is_one_line_naming_the_file_or_option() {
    let series = |est: &'static str, truth: &'static str, i: &'static str, k: &'static str| {
        plot_error(&[
            "series",
            "--estimates",
            est,
            "--truth",
            truth,
            "--subsystem",
            i,
            "--state",
            k,
        ])
    };
    let line = series("missing.csv", "platoon/truth.csv", "1", "1");
    assert!(line.contains("missing.csv"), "{line}");
    let line = series("paper/estimates.csv", "platoon/truth.csv", "1", "1");
    assert!(
        line.contains("paper/estimates.csv") && line.contains("platoon/truth.csv"),
        "{line}"
    );
    let line = series("platoon/estimates.csv", "platoon/truth.csv", "21", "1");
    assert!(
        line.contains("--subsystem 21") && line.contains("1..20"),
        "{line}"
    );
    let line = series("platoon/estimates.csv", "platoon/truth.csv", "0", "1");
    assert!(line.contains("--subsystem 0"), "{line}");
    let line = series("platoon/estimates.csv", "platoon/truth.csv", "1", "3");
    assert!(
        line.contains("--state 3") && line.contains("1..2"),
        "{line}"
    );
    // The truth given as estimates: wrong columns, named.
    let line = series("platoon/truth.csv", "platoon/truth.csv", "1", "1");
    assert!(
        line.contains("platoon/truth.csv: line 1") && line.contains("estimates"),
        "{line}"
    );

    // Estimates that stop early.
    let dir = fixture();
    let text = std::fs::read_to_string(dir.join("platoon/estimates.csv")).unwrap();
    let short: Vec<&str> = text.lines().take(1 + 20 * 50).collect();
    std::fs::write(dir.join("short.csv"), short.join("\n") + "\n").unwrap();
    let line = plot_error(&[
        "heatmap",
        "--estimates",
        "short.csv",
        "--truth",
        "platoon/truth.csv",
    ]);
    assert!(
        line.contains("short.csv") && line.contains("t = 50"),
        "{line}"
    );
    let line = plot_error(&[
        "heatmap",
        "--estimates",
        "platoon/estimates.csv",
        "--truth",
        "platoon/truth.csv",
        "--state",
        "9",
    ]);
    assert!(line.contains("--state 9"), "{line}");

    // Measurements of another chain.
    let line = plot_error(&[
        "series",
        "--estimates",
        "platoon/estimates.csv",
        "--truth",
        "platoon/truth.csv",
        "--meas",
        "paper/measurements.csv",
        "--subsystem",
        "1",
        "--state",
        "1",
    ]);
    assert!(line.contains("paper/measurements.csv"), "{line}");

    // Not an evaluation.
    let line = plot_error(&["evaluate", "--input", "platoon/truth.csv"]);
    assert!(line.contains("platoon/truth.csv"), "{line}");
    let line = plot_error(&["evaluate", "--input", "platoon/run.json"]);
    assert!(line.contains("platoon/run.json"), "{line}");
    let line = plot_error(&["evaluate", "--input", "nothing.json"]);
    assert!(line.contains("nothing.json"), "{line}");
}

#[test]
fn completions_for_bash_zsh_and_fish() {
    for shell in ["bash", "zsh", "fish"] {
        let out = sisfilt().args(["completions", shell]).assert().success();
        let script = String::from_utf8(out.get_output().stdout.clone()).unwrap();
        assert!(script.len() > 1000, "{shell}: {} bytes", script.len());
        for word in [
            "simulate",
            "estimate",
            "evaluate",
            "plot",
            "heatmap",
            // Options: fish writes them without the dashes (`-l subsystem`).
            "sweep-p",
            "subsystem",
        ] {
            assert!(script.contains(word), "{shell} script lacks {word}");
        }
    }
    sisfilt().args(["completions", "tcsh"]).assert().code(2);
}

#[test]
fn man_pages_for_sisfilt_and_its_commands() {
    let page = |args: &[&str]| {
        let out = sisfilt().arg("man").args(args).assert().success();
        String::from_utf8(out.get_output().stdout.clone()).unwrap()
    };
    let top = page(&[]);
    assert!(
        top.contains(".TH sisfilt 1"),
        "{}",
        &top[..200.min(top.len())]
    );
    assert!(top.contains("simulate") && top.contains("plot"));
    let series = page(&["plot", "series"]);
    assert!(
        series.contains(".TH sisfilt\\-plot\\-series 1")
            || series.contains(".TH sisfilt-plot-series 1"),
        "{}",
        &series[..300.min(series.len())]
    );
    assert!(series.contains("subsystem") && series.contains("smoothed"));
    let out = sisfilt().args(["man", "plot", "bogus"]).assert().code(2);
    let line = one_error_line(&out.get_output().stderr);
    assert!(line.contains("bogus") && line.contains("heatmap"), "{line}");
}

#[test]
fn quiet_drops_warnings_and_verbose_adds_info_lines() {
    let dir = fixture();
    // paper.toml has Q = 0 on a coupled chain: `estimate` warns.
    let run = |flag: Option<&str>| {
        let mut cmd = sisfilt();
        cmd.current_dir(dir);
        if let Some(f) = flag {
            cmd.arg(f);
        }
        let out = cmd
            .args([
                "estimate",
                "--meas",
                "paper/measurements.csv",
                "--out",
                "paper/quiet.csv",
            ])
            .assert()
            .success();
        String::from_utf8(out.get_output().stderr.clone()).unwrap()
    };
    let normal = run(None);
    assert!(
        normal.lines().any(|l| l.starts_with("warning: ")),
        "{normal}"
    );
    assert!(
        normal
            .lines()
            .all(|l| ["warning: ", "accuracy: ", "innovations: "]
                .iter()
                .any(|kind| l.starts_with(kind))),
        "{normal}"
    );
    assert_eq!(run(Some("--quiet")), "");
    assert_eq!(run(Some("-q")), "");
    let verbose = run(Some("--verbose"));
    assert!(
        verbose.lines().any(|l| l.starts_with("warning: ")),
        "{verbose}"
    );
    assert!(
        verbose.lines().any(|l| l.starts_with("info: ")),
        "{verbose}"
    );
    assert!(
        verbose
            .lines()
            .all(|l| ["warning: ", "info: ", "innovations: "]
                .iter()
                .any(|kind| l.starts_with(kind))),
        "{verbose}"
    );
    // The flags are global: after the command too. Both together are a usage error.
    sisfilt()
        .current_dir(dir)
        .args([
            "check",
            shipped_config("paper.toml").to_str().unwrap(),
            "-q",
        ])
        .assert()
        .success();
    let out = sisfilt()
        .args(["-q", "-v", "check", "x.toml"])
        .assert()
        .code(2);
    one_error_line(&out.get_output().stderr);
}

/// Without `--truth`, `plot heatmap` maps `√NIS` from the estimates' `nis` column, from the
/// CSV and the JSON of the joint filter with the mixture update (cross-covariance and
/// `arrival` columns before `nis`), the same from both. A sensor with an offset of 1 (five
/// of its noise's standard deviations) shows as a stripe: the map's row of that subsystem averages far above the others (read through
/// the library), and `estimate` names it. Estimates without the `nis` column are refused,
/// naming the option that writes it.
#[test]
fn heatmap_without_truth_maps_the_innovations_and_shows_a_faulty_sensor() {
    let dir = fixture();
    // Subsystem 7's sensor reads 1 too high (a miscalibrated radar and odometer).
    let meas = std::fs::read_to_string(dir.join("platoon/measurements.csv")).unwrap();
    let stuck: String = meas
        .lines()
        .map(|l| {
            let cells: Vec<&str> = l.split(',').collect();
            if cells[1] == "7" {
                let y = |k: usize| cells[k].parse::<f64>().unwrap() + 1.0;
                format!("{},{},{},{}\n", cells[0], cells[1], y(2), y(3))
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    std::fs::write(dir.join("platoon/stuck.csv"), stuck).unwrap();
    let mut outputs = Vec::new();
    for out in ["platoon/nis.csv", "platoon/nis_.json"] {
        let assert = run_ok(
            dir,
            &[
                "estimate",
                "--meas",
                "platoon/stuck.csv",
                "--inputs",
                "platoon/inputs.csv",
                "--filter",
                "joint",
                "--update",
                "mixture",
                "--nis",
                "--out",
                out,
            ],
        );
        let stderr = String::from_utf8(assert.get_output().stderr.clone()).unwrap();
        assert!(
            stderr.contains("some subsystems stand out from the others: i = 7 "),
            "{stderr}"
        );
        let svg = plot(&["heatmap", "--estimates", out], &format!("{out}.svg"));
        let texts = texts(&svg);
        assert_has_part(&texts, "Normalised innovations √NIS along the chain");
        outputs.push(svg);
    }
    assert!(outputs[0].replace("nis.csv", "E") == outputs[1].replace("nis_.json", "E"));
    let map = sisfilt::plot::heatmap::read(&sisfilt::plot::heatmap::HeatmapPlot {
        estimates: dir.join("platoon/nis.csv"),
        truth: None,
        state: 1,
        plain: false,
        out: dir.join("unused.svg"),
    })
    .unwrap();
    assert_eq!((map.steps, map.subsystems), (200, 20));
    let mean_nis = |i: usize| {
        (0..map.steps)
            .map(|t| map.values[t * 20 + i - 1].powi(2))
            .sum::<f64>()
            / map.steps as f64
    };
    let others: f64 = (1..=20).filter(|&i| i != 7).map(mean_nis).sum::<f64>() / 19.0;
    assert!(
        mean_nis(7) > 10.0 * others,
        "{} against {others}",
        mean_nis(7)
    );
    let err = plot_error(&["heatmap", "--estimates", "platoon/estimates.csv"]);
    assert!(
        err.contains("platoon/estimates.csv") && err.contains("estimate --nis"),
        "{err}"
    );
}

/// Without `--truth`, `plot series` draws the estimate with its band and the measurements
/// (coloured by `π` with the mixture update), and below, the NIS of each measurement with
/// the `χ²_q` band (q from the measurements), from the estimates' `nis` column: the same
/// figure from the CSV and the JSON of the joint filter. The share of NIS points inside the
/// band in the legend is recomputed here from the `nis` column. Estimates without the column
/// give the top panel alone, with a warning naming `estimate --nis`.
#[test]
fn series_without_truth_draws_the_innovations() {
    let dir = fixture();
    joint_mixture_estimates(
        "platoon",
        &["--nis"],
        ["platoon/joint_nis.csv", "platoon/joint_ni.json"],
    );
    let args = |est: &'static str| {
        vec![
            "series",
            "--estimates",
            est,
            "--meas",
            "platoon/measurements.csv",
            "--subsystem",
            "4",
            "--state",
            "1",
        ]
    };
    let csv = plot(&args("platoon/joint_nis.csv"), "series-nis-csv.svg");
    let json = plot(&args("platoon/joint_ni.json"), "series-nis-json.svg");
    assert!(csv.replace("joint_nis.csv", "E") == json.replace("joint_ni.json", "E"));
    let texts = texts(&csv);
    assert_has_part(
        &texts,
        "(no truth: the innovations tell how well the model fits)",
    );
    assert_has_part(&texts, "Normalised innovation squared");
    assert!(!texts.iter().any(|t| t == "truth"), "{texts:#?}");
    let est = Csv::read(&dir.join("platoon/joint_nis.csv"));
    let nis = column(&est, "nis", 4);
    // χ²₂: 0.0506 and 7.3778 (standard tables).
    let inside = nis
        .iter()
        .filter(|&&v| (0.0506..=7.3778).contains(&v))
        .count();
    let share = format!("{:.1} % inside", 100.0 * inside as f64 / nis.len() as f64);
    assert_has_part(&texts, &share);
    assert_has_part(&texts, "95 % band of a model that fits, χ²_2");
    // Estimates without the nis column: the top panel alone, and a warning.
    let out = sisfilt()
        .current_dir(dir)
        .args([
            "plot",
            "series",
            "--estimates",
            "platoon/estimates.csv",
            "--subsystem",
            "4",
        ])
        .args(["--state", "1", "--out", "series-no-nis.svg"])
        .assert()
        .success();
    let stderr = String::from_utf8(out.get_output().stderr.clone()).unwrap();
    assert!(
        stderr.contains("has no `nis` column") && stderr.contains("estimate --nis"),
        "{stderr}"
    );
    let texts = self::texts(&std::fs::read_to_string(dir.join("series-no-nis.svg")).unwrap());
    assert!(
        !texts.iter().any(|t| t.contains("Normalised innovation")),
        "{texts:#?}"
    );
}
