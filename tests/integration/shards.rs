//! A study cut into shards (`evaluate --shard K/M`), run as separate processes side by side and
//! added up by `evaluate-merge`, reports what one `evaluate` of the whole study reports (the
//! same sums added in another grouping: equal to 1e−12 relative); parts that are not one
//! study are refused, naming their files.

use std::path::{Path, PathBuf};

use crate::common::{one_error_line, shipped_config, sisfilt};

/// The JSON in `path`.
fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// Asserts that `a` and `b` hold the same keys, strings, integers and `null`s, and numbers
/// within `rel` of each other, but for the clock readings (keys with `time`); the largest
/// relative gap.
fn assert_close(a: &serde_json::Value, b: &serde_json::Value, rel: f64, at: &str) -> f64 {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let keys = |m: &serde_json::Map<String, Value>| m.keys().cloned().collect::<Vec<_>>();
            assert_eq!(keys(x), keys(y), "{at}");
            x.iter()
                .filter(|(k, _)| !k.contains("time"))
                .map(|(k, v)| assert_close(v, &y[k], rel, &format!("{at}.{k}")))
                .fold(0.0, f64::max)
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            x.iter()
                .zip(y)
                .enumerate()
                .map(|(i, (u, v))| assert_close(u, v, rel, &format!("{at}[{i}]")))
                .fold(0.0, f64::max)
        }
        (Value::Number(x), Value::Number(y)) if x.is_f64() || y.is_f64() => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            let gap = (x - y).abs() / x.abs().max(y.abs()).max(f64::MIN_POSITIVE);
            assert!(gap <= rel, "{at}: {x} and {y}");
            gap
        }
        _ => {
            assert_eq!(a, b, "{at}");
            0.0
        }
    }
}

/// Runs `evaluate` of `paper.toml` with `args`, once whole and as four shards side by side
/// (separate processes), merges the parts and compares; the parts' files.
fn four_shards_merge_to_the_whole(dir: &Path, args: &[&str]) -> Vec<PathBuf> {
    let config = shipped_config("paper.toml");
    let whole = dir.join("whole.json");
    sisfilt()
        .arg("evaluate")
        .arg(&config)
        .args(args)
        .arg("--out")
        .arg(&whole)
        .assert()
        .success();
    let parts: Vec<PathBuf> = (0..4).map(|k| dir.join(format!("part-{k}.json"))).collect();
    let running: Vec<std::process::Child> = parts
        .iter()
        .enumerate()
        .map(|(k, part)| {
            std::process::Command::new(env!("CARGO_BIN_EXE_sisfilt"))
                .arg("evaluate")
                .arg(&config)
                .args(args)
                .args(["--shard", &format!("{k}/4"), "--out"])
                .arg(part)
                .env("RAYON_NUM_THREADS", "1")
                .stdout(std::process::Stdio::null())
                .spawn()
                .unwrap()
        })
        .collect();
    for mut child in running {
        assert!(child.wait().unwrap().success());
    }
    let merged = dir.join("merged.json");
    // Any order of the parts on the command line.
    let out = sisfilt()
        .arg("evaluate-merge")
        .args(parts.iter().rev())
        .arg("--out")
        .arg(&merged)
        .assert()
        .success();
    let gap = assert_close(&json(&whole), &json(&merged), 1e-12, "");
    eprintln!("largest relative gap, merged against whole: {gap:.2e}");
    // The table is the whole study's (its clock column aside).
    let table = String::from_utf8_lossy(&out.get_output().stdout).to_string();
    assert!(
        table.contains("paper.toml: 40 runs (seeds 3..42)"),
        "{table}"
    );
    parts
}

#[test]
fn four_shards_merge_to_the_whole_study_with_smoothers() {
    let dir = tempfile::tempdir().unwrap();
    let args = ["--runs", "40", "--seed", "3", "--smooth"];
    let parts = four_shards_merge_to_the_whole(dir.path(), &args);
    // Each part holds its block of runs, with the sums per state element and per step.
    for (k, part) in parts.iter().enumerate() {
        let part = json(part);
        assert_eq!(part["shard"], serde_json::json!({"index": k, "count": 4}));
        assert_eq!(part["runs"], serde_json::json!([10 * k, 10 * k + 10]));
        let first = &part["studies"][0]["filters"][0];
        assert_eq!(
            first["scores"]["accuracy"]["sum_sq"]
                .as_array()
                .unwrap()
                .len(),
            2
        );
        assert_eq!(
            first["scores"]["per_step"]["sum"].as_array().unwrap().len(),
            150
        );
        assert_eq!(first["scores"]["accuracy"]["runs"], 10);
    }
    // `plot evaluate` draws the merged study and sends a part back to the merge.
    let svg = dir.path().join("merged.svg");
    sisfilt()
        .args(["plot", "evaluate", "--input"])
        .arg(dir.path().join("merged.json"))
        .arg("--out")
        .arg(&svg)
        .assert()
        .success();
    let refused = sisfilt()
        .args(["plot", "evaluate", "--input"])
        .arg(&parts[0])
        .arg("--out")
        .arg(dir.path().join("part.svg"))
        .assert()
        .code(2);
    let line = one_error_line(&refused.get_output().stderr);
    assert!(
        line.contains("part-0.json") && line.contains("evaluate-merge"),
        "{line}"
    );
}

#[test]
fn four_shards_merge_to_the_whole_sweep_with_a_true_p() {
    let dir = tempfile::tempdir().unwrap();
    let args = [
        "--runs",
        "40",
        "--sweep-p",
        "0.6,0.9",
        "--true-p",
        "0.8",
        "--filters",
        "distributed,joint,centralized,joint-mixture",
    ];
    four_shards_merge_to_the_whole(dir.path(), &args);
}

/// Runs one shard of `paper.toml` (`--runs 8`) with `extra` into `dir/name`.
fn part(dir: &Path, name: &str, shard: &str, extra: &[&str]) -> PathBuf {
    let path = dir.join(name);
    sisfilt()
        .arg("evaluate")
        .arg(shipped_config("paper.toml"))
        .args(["--runs", "8", "--filters", "joint", "--shard", shard])
        .args(extra)
        .arg("--out")
        .arg(&path)
        .assert()
        .success();
    path
}

/// The one error line of `evaluate-merge` of `parts` (exit 2), which writes nothing.
fn refused(dir: &Path, parts: &[&PathBuf]) -> String {
    let out = dir.join("merged.json");
    let run = sisfilt()
        .arg("evaluate-merge")
        .args(parts)
        .arg("--out")
        .arg(&out)
        .assert()
        .code(2);
    assert!(!out.exists());
    one_error_line(&run.get_output().stderr)
}

#[test]
fn a_missing_a_duplicated_and_a_foreign_shard_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let p0 = part(d, "p0.json", "0/3", &[]);
    let p1 = part(d, "p1.json", "1/3", &[]);
    let p2 = part(d, "p2.json", "2/3", &[]);
    let again = part(d, "again.json", "1/3", &[]);
    let line = refused(d, &[&p0, &p2]);
    assert!(
        line.contains("shard 1/3") && line.contains("missing"),
        "{line}"
    );
    let line = refused(d, &[&p0, &p1, &again, &p2]);
    assert!(
        line.contains("again.json") && line.contains("p1.json") && line.contains("shard 1/3"),
        "{line}"
    );
    // Another model (a --set value), other options, another cut.
    let other_p = part(d, "other-p.json", "1/3", &["--set", "dropout.p=0.5"]);
    let line = refused(d, &[&p0, &other_p, &p2]);
    assert!(
        line.contains("other-p.json") && line.contains("models differ"),
        "{line}"
    );
    let other_seed = part(d, "other-seed.json", "1/3", &["--seed", "99"]);
    let line = refused(d, &[&p0, &other_seed, &p2]);
    assert!(
        line.contains("other-seed.json") && line.contains("options differ"),
        "{line}"
    );
    let halves = part(d, "half.json", "1/2", &[]);
    let line = refused(d, &[&p0, &halves, &p2]);
    assert!(
        line.contains("half.json") && line.contains("shard counts"),
        "{line}"
    );
    // A file that is no part at all.
    let table = crate::common::write_file(d, "table.json", "{\"filters\": []}");
    let line = refused(d, &[&p0, &table]);
    assert!(
        line.contains("table.json: line 1") && line.contains("evaluate --shard"),
        "{line}"
    );
    // Parts edited by hand: sums of another length; a count far above the parts given, whose
    // missing shards are named a few at a time.
    let edited = |name: &str, edit: &dyn Fn(&mut serde_json::Value)| {
        let mut doc = json(&p0);
        edit(&mut doc);
        crate::common::write_file(d, name, &doc.to_string())
    };
    let short = edited("short.json", &|doc| {
        doc["studies"][0]["filters"][0]["scores"]["per_step"]["sum"] = serde_json::json!([1.0]);
    });
    let line = refused(d, &[&short, &p1, &p2]);
    assert!(line.contains("short.json: not a part written by"), "{line}");
    let huge = edited("huge.json", &|doc| {
        doc["shard"]["count"] = serde_json::json!(1u64 << 60);
        doc["options"]["runs"] = serde_json::json!(1u64 << 60);
        doc["runs"] = serde_json::json!([0, 1]);
    });
    let line = refused(d, &[&huge]);
    assert!(
        line.contains("shard 5/1152921504606846976, and 1152921504606846970 more"),
        "{line}"
    );
    // The three together are the study.
    sisfilt()
        .arg("evaluate-merge")
        .args([&p2, &p0, &p1])
        .assert()
        .success();
}

#[test]
fn a_shard_out_of_range_or_more_shards_than_runs_is_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    for (shard, runs, expected) in [
        ("4/4", "8", "expected K/M with 0 ≤ K < M"),
        ("1/0", "8", "expected K/M"),
        ("a/4", "8", "expected K/M"),
        ("3/16", "8", "at most one shard per run"),
    ] {
        let run = sisfilt()
            .arg("evaluate")
            .arg(shipped_config("paper.toml"))
            .args(["--runs", runs, "--shard", shard, "--out"])
            .arg(dir.path().join("p.json"))
            .assert()
            .code(2);
        let stderr = String::from_utf8_lossy(&run.get_output().stderr).to_string();
        assert!(stderr.contains(expected), "{shard}: {stderr}");
    }
    // A part goes to a file.
    sisfilt()
        .arg("evaluate")
        .arg(shipped_config("paper.toml"))
        .args(["--runs", "8", "--shard", "0/2"])
        .assert()
        .code(2);
}

/// A folder as a user's: `configs/platoon.toml`, with this build's `sisfilt` first on `PATH`.
fn user_folder() -> (tempfile::TempDir, std::ffi::OsString) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("configs")).unwrap();
    std::fs::copy(
        shipped_config("platoon.toml"),
        dir.path().join("configs/platoon.toml"),
    )
    .unwrap();
    let bin = Path::new(env!("CARGO_BIN_EXE_sisfilt")).parent().unwrap();
    let path = std::env::join_paths(std::iter::once(bin.to_path_buf()).chain(
        std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()),
    ))
    .unwrap();
    (dir, path)
}

/// Runs `script` with `bash -c` (which runs the pods' `sh -c` lines alike) in `dir`, with `PATH`
/// and `env` set.
fn shell(dir: &Path, path: &std::ffi::OsStr, script: &str, env: &[(&str, String)]) {
    let out = std::process::Command::new("bash")
        .args(["-c", script])
        .current_dir(dir)
        .env("PATH", path)
        .envs(env.iter().map(|(k, v)| (k, v)))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{script}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The JSON of one `evaluate configs/platoon.toml` in `dir` with `args`, against `merged`.
fn merged_equals_the_whole(dir: &Path, merged: &Path, args: &[&str]) {
    let whole = dir.join("whole.json");
    sisfilt()
        .current_dir(dir)
        .args(["evaluate", "configs/platoon.toml"])
        .args(args)
        .arg("--out")
        .arg(&whole)
        .assert()
        .success();
    let gap = assert_close(&json(&whole), &json(merged), 1e-12, "");
    eprintln!("{}: largest relative gap {gap:.2e}", merged.display());
}

/// The text of the repository's file `path`.
fn shipped(path: &str) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(path)).unwrap()
}

/// The first line of `text` that holds `what`, as a command (a YAML list item's `- ` and a
/// shell line's continuation joined).
fn command_line(text: &str, what: &str) -> String {
    let joined = text.replace("\\\n", " ");
    let line = joined.lines().find(|l| l.contains(what)).unwrap();
    line.trim().trim_start_matches("- ").to_string()
}

/// The README's GNU parallel recipe as written but for the number of runs, where GNU parallel
/// is installed (else said on standard error).
#[test]
fn the_readmes_gnu_parallel_recipe() {
    let readme = shipped("README.md");
    let recipe = readme
        .split("<!-- recipe: parallel -->\n```sh\n")
        .nth(1)
        .and_then(|rest| rest.split("```\n<!-- end recipe -->").next())
        .expect("the README's GNU parallel recipe");
    assert!(recipe.contains("--runs 800 --shard {}/8"), "{recipe}");
    let has_parallel = std::process::Command::new("parallel")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_parallel {
        eprintln!("skipped: GNU parallel is not installed");
        return;
    }
    let (dir, path) = user_folder();
    shell(
        dir.path(),
        &path,
        &recipe.replace("--runs 800", "--runs 24"),
        &[],
    );
    merged_equals_the_whole(
        dir.path(),
        &dir.path().join("study.json"),
        &["--runs", "24"],
    );
}

/// The Slurm job array as Slurm runs it (each task with its `SLURM_ARRAY_TASK_ID`; the
/// `#SBATCH` lines are comments to the shell) but for the number of runs, then the merge of
/// its header's second job.
#[test]
fn the_slurm_array_recipe_as_slurm_runs_it() {
    let script = shipped("examples/cluster/slurm-array.sh");
    assert!(script.contains("#SBATCH --array=0-63") && script.contains("--runs 6400"));
    let script = script.replace("--runs 6400", "--runs 64");
    let merge = command_line(&script, "--wrap");
    let merge = merge.split('\'').nth(1).expect("the merge job's command");
    let (dir, path) = user_folder();
    for task in 0..64 {
        shell(
            dir.path(),
            &path,
            &script,
            &[
                ("SLURM_ARRAY_TASK_ID", task.to_string()),
                ("SLURM_CPUS_PER_TASK", "1".into()),
            ],
        );
    }
    shell(dir.path(), &path, merge, &[]);
    merged_equals_the_whole(
        dir.path(),
        &dir.path().join("study.json"),
        &["--runs", "64", "--smooth"],
    );
}

/// The Kubernetes Indexed Job's command as each pod runs it (`JOB_COMPLETION_INDEX`), with the
/// volumes as folders and fewer runs, then the merge Job's command.
#[test]
fn the_kubernetes_indexed_job_recipe_as_its_pods_run_it() {
    let job = shipped("examples/cluster/k8s-indexed-job.yaml");
    assert!(job.contains("completionMode: Indexed") && job.contains("completions: 16"));
    let local = |command: String| {
        command
            .replace("/configs/", "configs/")
            .replace("/parts/", "parts/")
            .replace("--runs 1600", "--runs 32")
    };
    let shard = local(command_line(&job, "sisfilt evaluate "));
    let merge = local(command_line(
        &shipped("examples/cluster/k8s-merge-job.yaml"),
        "sisfilt evaluate-merge",
    ));
    let (dir, path) = user_folder();
    std::fs::create_dir(dir.path().join("parts")).unwrap();
    for index in 0..16 {
        shell(
            dir.path(),
            &path,
            &shard,
            &[("JOB_COMPLETION_INDEX", index.to_string())],
        );
    }
    shell(dir.path(), &path, &merge, &[]);
    merged_equals_the_whole(
        dir.path(),
        &dir.path().join("parts/study.json"),
        &["--runs", "32", "--smooth"],
    );
}
