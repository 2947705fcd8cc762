//! `sisfilt evaluate` from the command line: the table, the JSON, and independence of the
//! thread count.

use crate::common::{shipped_config, sisfilt};

/// Removes every key whose name contains `time` (the only clock readings, docs/theory.md §13).
fn strip_times(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Object(map) => {
            map.retain(|k, _| !k.contains("time"));
            map.values_mut().for_each(strip_times);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(strip_times),
        _ => {}
    }
}

fn evaluate_json(threads: &str, dir: &std::path::Path) -> serde_json::Value {
    let out = dir.join(format!("eval{threads}.json"));
    sisfilt()
        .env("RAYON_NUM_THREADS", threads)
        .arg("evaluate")
        .arg(shipped_config("paper.toml"))
        .args(["--runs", "12", "--seed", "5", "--out"])
        .arg(&out)
        .assert()
        .success();
    serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap()
}

#[test]
fn same_results_with_one_and_two_threads() {
    let dir = tempfile::tempdir().unwrap();
    let mut one = evaluate_json("1", dir.path());
    let mut two = evaluate_json("2", dir.path());
    strip_times(&mut one);
    strip_times(&mut two);
    assert_eq!(one, two);
    // The JSON names every filter of docs/theory.md §13, with figures.
    let names: Vec<&str> = one["filters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        [
            "distributed",
            "distributed-paper",
            "joint",
            "centralized",
            "centralized-known",
            "naive",
            "distributed-mixture",
            "joint-mixture",
            "centralized-mixture"
        ]
    );
    let central = &one["filters"][3];
    assert_eq!(central["rmse_ratio"].as_f64(), Some(1.0));
    assert!(central["accuracy"]["anees"].as_f64().is_some());
    // Every filter carries its average NEES per time step (T = 150 for paper.toml).
    for f in one["filters"].as_array().unwrap() {
        assert_eq!(
            f["nees_per_step"].as_array().unwrap().len(),
            150,
            "{}",
            f["name"]
        );
    }
}

/// `--smooth` adds the smoother rows (one per filter of `estimate`), each with its ratio to the centralized smoother
/// and to the centralized filter; smoothing beats filtering.
#[test]
fn smooth_adds_the_smoother_rows() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("eval.json");
    sisfilt()
        .arg("evaluate")
        .arg(shipped_config("paper.toml"))
        .args(["--runs", "4", "--smooth", "--out"])
        .arg(&out)
        .assert()
        .success();
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap();
    let filters = v["filters"].as_array().unwrap();
    assert_eq!(filters.len(), 15);
    for name in [
        "distributed-smoother",
        "joint-smoother",
        "centralized-smoother",
        "distributed-mixture-smoother",
        "centralized-mixture-smoother",
    ] {
        let f = filters.iter().find(|f| f["name"] == name).unwrap();
        assert!(f["rmse_ratio"].as_f64().is_some(), "{name}");
        assert!(f["rmse_ratio_to_filter"].as_f64().unwrap() < 1.0, "{name}");
    }
}

#[test]
fn table_lists_filters_and_notes_skipped_ones() {
    let out = sisfilt()
        .arg("evaluate")
        .arg(shipped_config("platoon.toml"))
        .args(["--runs", "3"])
        .assert()
        .success();
    let stdout = String::from_utf8(out.get_output().stdout.clone()).unwrap();
    for name in [
        "distributed",
        "centralized",
        "centralized-known",
        "naive",
        "ANEES",
    ] {
        assert!(stdout.contains(name), "{stdout}");
    }
    // The platoon has G22 = 0, so the paper's transfer solver cannot run: skipped with a note.
    assert!(
        stdout
            .lines()
            .any(|l| l.starts_with("distributed-paper ") && l.contains("skipped")),
        "{stdout}"
    );
    assert!(stdout.contains("note: distributed-paper"), "{stdout}");

    // Above the size limit the centralized filters are skipped, with a note.
    let out = sisfilt()
        .arg("evaluate")
        .arg(shipped_config("platoon.toml"))
        .args(["--runs", "2", "--max-lifted", "10"])
        .assert()
        .success();
    let stdout = String::from_utf8(out.get_output().stdout.clone()).unwrap();
    assert!(
        stdout.contains("note: centralized:") && stdout.contains("--max-lifted"),
        "{stdout}"
    );
}

/// A chain whose predicted covariance is singular (`Q = 0`, rank-one `A`, no coupling out of
/// the states): `evaluate --smooth` smooths it through the pseudo-inverse of `T(t+1)`
/// (docs/theory.md §9) with nothing to warn about, and the centralized smoother's row beats
/// its filter.
#[test]
fn smoothers_run_on_a_singular_prediction() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("singular.toml");
    std::fs::write(
        &config,
        "subsystems = 3\nsteps = 12\nseed = 2\n[interconnection]\nplus = 1\nminus = 1\n\
         [model]\nA = [[0.8, 0.4], [0.4, 0.2]]\nB = [[0.3, 0.1], [0.1, 0.25]]\n\
         D = [[0.5, 0.1], [0.2, 0.6]]\nG = [[0.2, 0.3], [0.25, 0.15]]\nH = [[0.0], [0.0]]\n\
         J = [[1.0, 0.5]]\nM = [[0.2]]\nQ = [[0.0, 0.0], [0.0, 0.0]]\n[dropout]\np = 0.7\n[initial]\ncov = [[0.8, 0.1], [0.1, 0.4]]\n",
    )
    .unwrap();
    let out = dir.path().join("eval.json");
    let run = sisfilt()
        .arg("evaluate")
        .arg(&config)
        .args(["--runs", "20", "--smooth", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(!stderr.contains("centralized-smoother"), "{stderr}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap();
    let row = v["filters"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["name"] == "centralized-smoother")
        .unwrap();
    assert!(row["skipped"].is_null(), "{row}");
    assert_eq!(row["notes"].as_array().map_or(0, Vec::len), 0, "{row}");
    assert!(row["rmse_ratio_to_filter"].as_f64().unwrap() < 1.0);
}

/// A filter whose estimates overflow in a run (the paper's transfer recursion on a rod of 400
/// segments) is reported as failed, naming the run, `t` and `i`; none of its numbers reach
/// the table or the JSON, and the other filters keep their figures.
#[test]
fn a_filter_that_breaks_down_is_named_with_its_run_and_writes_no_figures() {
    let dir = tempfile::tempdir().unwrap();
    let rod = std::fs::read_to_string(shipped_config("heat_rod.toml")).unwrap();
    let long_rod: String = rod
        .lines()
        .map(|l| match l.split_once(" = ").map(|(k, _)| k) {
            Some("subsystems") => "subsystems = 400".to_string(),
            Some("steps") => "steps = 5".to_string(),
            _ => l.to_string(),
        })
        .collect::<Vec<_>>()
        .join("\n");
    let config = dir.path().join("long_rod.toml");
    std::fs::write(&config, long_rod).unwrap();
    let out = dir.path().join("eval.json");
    let run = sisfilt()
        .arg("evaluate")
        .arg(&config)
        .args([
            "--runs",
            "2",
            "--filters",
            "distributed,distributed-paper",
            "--out",
        ])
        .arg(&out)
        .assert()
        .success();
    let table = String::from_utf8_lossy(&run.get_output().stdout).to_string();
    assert!(
        table.contains("note: distributed-paper: failed: run 1, t = 1, i = "),
        "{table}"
    );
    let rows = table.lines().skip(3).take_while(|l| !l.is_empty());
    for row in rows {
        assert!(!row.contains("inf") && !row.contains("NaN"), "{row}");
    }
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap();
    let filters = doc["filters"].as_array().unwrap();
    let by_name = |name: &str| filters.iter().find(|f| f["name"] == name).unwrap();
    let paper = by_name("distributed-paper");
    assert!(paper["accuracy"].is_null(), "{paper}");
    assert!(
        paper["skipped"]
            .as_str()
            .unwrap()
            .starts_with("failed: run 1, t = 1, i = "),
        "{paper}"
    );
    let rmse = by_name("distributed")["accuracy"]["rmse_overall"]
        .as_f64()
        .unwrap();
    assert!(rmse.is_finite() && rmse > 0.0, "{rmse}");
}

/// The JSON of `evaluate --out` (one evaluation, or a sweep over `p`) is one library type: it
/// reads back whole into `Evaluation` or `Sweep` and writes the same document again, the
/// overflowed RMSE of the paper's filter on the heat rod (`null`) included.
#[test]
fn the_json_reads_back_into_the_library_types_without_loss() {
    use sisfilt::evaluate::{Evaluation, Sweep};
    let dir = tempfile::tempdir().unwrap();
    let run = |config: &str, extra: &[&str], name: &str| -> (String, serde_json::Value) {
        let out = dir.path().join(name);
        sisfilt()
            .arg("evaluate")
            .arg(shipped_config(config))
            .args(["--runs", "2", "--smooth", "--out"])
            .arg(&out)
            .args(extra)
            .assert()
            .success();
        let text = std::fs::read_to_string(out).unwrap();
        let value = serde_json::from_str(&text).unwrap();
        (text, value)
    };
    let (text, written) = run("heat_rod.toml", &[], "single.json");
    let overflowed = &written["filters"][1];
    assert_eq!(overflowed["name"], "distributed-paper");
    assert!(
        overflowed["accuracy"]["rmse_overall"].is_null(),
        "{overflowed}"
    );
    let single: Evaluation = serde_json::from_str(&text).unwrap();
    assert_eq!(single.filters.len(), 15);
    assert!(
        single.filters[1]
            .accuracy
            .as_ref()
            .unwrap()
            .rmse_overall
            .is_nan()
    );
    assert_eq!(serde_json::to_value(&single).unwrap(), written);

    let (text, written) = run("paper.toml", &["--sweep-p", "0.5,0.9"], "sweep.json");
    let sweep: Sweep = serde_json::from_str(&text).unwrap();
    assert_eq!(sweep.sweep_p, [0.5, 0.9]);
    assert_eq!(sweep.evaluations.len(), 2);
    assert_eq!(serde_json::to_value(&sweep).unwrap(), written);
}

/// `--true-p` changes the simulation only: the mixture rows' detection counts show the lost
/// share of the truth's `p` (0.4 lost with `--true-p 0.6`, 0.15 with the platoon's
/// `p = 0.85`; 12000 terms, so ±0.03 is over six standard deviations), over every scored
/// `(t, i)`; the filters keep the config's `p`, so the Nahi filter's ANEES leaves its band.
/// In a sweep the header says so and a block gives the share detected.
#[test]
fn true_p_simulates_another_arrival_probability_and_mixture_rows_score_detection() {
    let dir = tempfile::tempdir().unwrap();
    let run = |extra: &[&str]| -> (String, serde_json::Value) {
        let out = dir.path().join("eval.json");
        let assert = sisfilt()
            .arg("evaluate")
            .arg(shipped_config("platoon.toml"))
            .args([
                "--runs",
                "3",
                "--filters",
                "centralized,centralized-mixture",
            ])
            .args(extra)
            .arg("--out")
            .arg(&out)
            .assert()
            .success();
        let table = String::from_utf8(assert.get_output().stdout.clone()).unwrap();
        let json = serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap();
        (table, json)
    };
    for (extra, lost_share) in [(&["--true-p", "0.6"][..], 0.4), (&[][..], 0.15)] {
        let (table, v) = run(extra);
        assert_eq!(
            table.contains("simulated with p = 0.6"),
            !extra.is_empty(),
            "{table}"
        );
        let nahi = &v["filters"][0];
        assert!(nahi["detection"].is_null(), "{nahi}");
        let d = &v["filters"][1]["detection"];
        let count = |key: &str| d[key].as_u64().unwrap();
        assert_eq!(count("lost") + count("received"), 3 * 200 * 20);
        let share = count("lost") as f64 / 12000.0;
        assert!((share - lost_share).abs() < 0.03, "{share} {d}");
        assert!(count("detected") <= count("lost"));
        assert!(count("false_alarms") <= count("received"));
        assert!(table.contains("detected") && table.contains("false alarms"));
        let anees = nahi["accuracy"]["anees"].as_f64().unwrap();
        assert_eq!(anees > 2.0, !extra.is_empty(), "Nahi's ANEES {anees}");
    }
    let (table, v) = run(&["--true-p", "0.6", "--sweep-p", "0.6,0.85"]);
    assert!(
        table.contains(
            "p replaces the filters' arrival probability at every (t, i); simulated with p = 0.6"
        ),
        "{table}"
    );
    assert!(
        table.contains("lost measurements detected (π < 0.5)"),
        "{table}"
    );
    assert_eq!(v["options"]["true_p"].as_f64(), Some(0.6));
    // The same realisations for both values: only the filters' p differs.
    let lost = |k: usize| v["evaluations"][k]["filters"][1]["detection"]["lost"].clone();
    assert_eq!(lost(0), lost(1));
}

/// Where the joint smoother reruns with a larger loading (docs/theory.md §9; the joint
/// mixture smoother on `paper.toml` in most runs), its row is scored, not skipped, and one
/// note says in how many runs that happened.
#[test]
fn joint_smoother_reruns_are_counted_in_a_note() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("eval.json");
    let assert = sisfilt()
        .arg("evaluate")
        .arg(shipped_config("paper.toml"))
        .args(["--smooth", "--filters", "joint-mixture-smoother"])
        .args(["--runs", "4", "--out"])
        .arg(&out)
        .assert()
        .success();
    let stderr = String::from_utf8_lossy(&assert.get_output().stderr).to_string();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let row = json["filters"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["name"] == "joint-mixture-smoother")
        .unwrap();
    assert!(row["skipped"].is_null(), "{row}");
    assert!(row["accuracy"]["rmse_overall"].as_f64().unwrap() > 0.0);
    let notes = row["notes"].as_array().unwrap();
    assert_eq!(notes.len(), 1, "{notes:?}");
    let note = notes[0].as_str().unwrap();
    let (count, rest) = note.split_once(" of 4 runs; the first: ").expect(note);
    let count: usize = count.parse().expect(note);
    assert!((1..=4).contains(&count), "{note}");
    assert!(rest.contains("smoothed with --loading"), "{note}");
    assert!(stderr.contains(note), "{stderr}");
}

/// The paper's chain with its initial state known exactly (`cov = 0`), written into `dir`.
fn known_start(dir: &std::path::Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(shipped_config("paper.toml")).unwrap();
    crate::common::write_file(
        dir,
        "known.toml",
        &text.replace(
            "cov = [[1.0, 0.0], [0.0, 1.0]]",
            "cov = [[0.0, 0.0], [0.0, 0.0]]",
        ),
    )
}

/// A filter that breaks down is a failed row with its message (run, `t`, `i`) while the
/// others complete: with `--loading 0` the joint filters cannot start from a zero initial
/// covariance (exit 1 and no table before, from the covariance pass computed once for all
/// runs); with the default loading every filter and smoother runs and is scored, and follows
/// the known trajectory (the centralized smoothers through the pseudo-inverse of a zero
/// `T(t+1)`, docs/theory.md §9).
#[test]
fn a_filter_that_breaks_down_is_a_failed_row() {
    let dir = tempfile::tempdir().unwrap();
    let config = known_start(dir.path());
    let out = dir.path().join("eval.json");
    let filters = "distributed,distributed-paper,joint,centralized,centralized-known,naive,\
        distributed-mixture,joint-mixture,centralized-mixture,distributed-smoother,\
        joint-smoother,centralized-smoother,distributed-mixture-smoother,joint-mixture-smoother,\
        centralized-mixture-smoother";
    let run = |extra: &[&str]| {
        let assert = sisfilt()
            .arg("evaluate")
            .arg(&config)
            .args(["--filters", filters, "--runs", "2", "--out"])
            .arg(&out)
            .args(extra)
            .assert()
            .success();
        let stdout = String::from_utf8_lossy(&assert.get_output().stdout).to_string();
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
        (stdout, json)
    };
    let (table, json) = run(&["--loading", "0"]);
    for row in json["filters"].as_array().unwrap() {
        let name = row["name"].as_str().unwrap();
        if name.starts_with("joint") {
            let why = row["skipped"].as_str().expect(name);
            assert!(
                why.starts_with("failed: run 1, t = 1, i = 1: joint"),
                "{name}: {why}"
            );
            assert!(
                table.contains(&format!("{name:<28} failed (see note)")),
                "{table}"
            );
        } else {
            assert!(row["skipped"].is_null(), "{name}: {row}");
            assert!(
                row["accuracy"]["rmse_overall"].as_f64().unwrap() < 1e-12,
                "{name}"
            );
        }
    }
    let (table, json) = run(&[]);
    assert!(!table.contains("(see note)"), "{table}");
    for row in json["filters"].as_array().unwrap() {
        assert!(row["skipped"].is_null(), "{row}");
        assert!(
            row["accuracy"]["rmse_overall"].as_f64().unwrap() < 1e-6,
            "{row}"
        );
    }
}

/// A filter that would hold more than `--max-memory` is skipped with a note naming what it
/// needs, before anything is allocated, while the others run: on the platoon (`N = 20`, `n = 2`,
/// `q = 2`) the centralized filters' bound is `8 (20 (N n)² + 2 (N q)² + 2 (N q)(N n))` =
/// 307200 bytes, above 200 KiB.
#[test]
fn a_filter_over_max_memory_is_skipped_with_a_note() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("eval.json");
    sisfilt()
        .arg("evaluate")
        .arg(shipped_config("platoon.toml"))
        .args(["--runs", "2", "--max-memory", "200K", "--out"])
        .arg(&out)
        .assert()
        .success();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let (nn, nq) = (40.0_f64, 40.0_f64);
    let bound = 8.0 * (20.0 * nn * nn + 2.0 * nq * nq + 2.0 * nq * nn);
    for row in json["filters"].as_array().unwrap() {
        let name = row["name"].as_str().unwrap();
        if name.starts_with("centralized") {
            let why = row["skipped"].as_str().expect(name);
            assert!(
                why.contains(&format!(
                    "needs 300.0 KiB ({bound} bytes), above max_memory 200.0 KiB"
                )),
                "{name}: {why}"
            );
        } else if name != "distributed-paper" {
            assert!(row["skipped"].is_null(), "{name}: {row}");
        }
    }
}
