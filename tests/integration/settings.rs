//! `--set KEY=VALUE` (docs/theory.md §13): a config value over the file's, on every command that
//! reads a config, gives what the file edited by hand gives, is recorded in `run.json` and the
//! estimates' metadata, and is checked as the file is, naming its key and `--set`.

use std::path::{Path, PathBuf};

use crate::common::{one_error_line, run_ok_in, shipped_config, sisfilt, write_file};

/// The platoon config with `p = 0.85` and `M` replaced by hand, in `dir` (beside the shipped
/// one's inputs it needs none).
fn edited_platoon(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(shipped_config("platoon.toml")).unwrap();
    assert!(text.contains("p = 0.85") && text.contains("M = [[0.04, 0.0], [0.0, 0.01]]"));
    let edited = text.replace("p = 0.85", "p = 0.6").replace(
        "M = [[0.04, 0.0], [0.0, 0.01]]",
        "M = [[0.09, 0.0], [0.0, 0.02]]",
    );
    write_file(dir, "edited.toml", &edited)
}

const SETS: [&str; 4] = [
    "--set",
    "dropout.p=0.6",
    "--set",
    "model.M=[[0.09, 0.0], [0.0, 0.02]]",
];

/// `args` and then [`SETS`].
fn with_sets<'a>(args: &[&'a str]) -> Vec<&'a str> {
    [args, &SETS[..]].concat()
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn set_gives_what_the_edited_file_gives_on_every_command() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let edited = edited_platoon(dir);
    let shipped = shipped_config("platoon.toml");
    let (edited, shipped) = (edited.to_str().unwrap(), shipped.to_str().unwrap());

    // check: the same report but for its first line, which names the settings.
    let by_hand = run_ok_in(dir, &["check", edited]);
    let set = run_ok_in(dir, &with_sets(&["check", shipped]));
    let (by_hand, set) = (
        String::from_utf8(by_hand.stdout).unwrap(),
        String::from_utf8(set.stdout).unwrap(),
    );
    assert_eq!(
        set.lines().next().unwrap(),
        format!("config: {shipped} --set {} --set {}", SETS[1], SETS[3])
    );
    assert_eq!(
        by_hand.lines().skip(1).collect::<Vec<_>>(),
        set.lines().skip(1).collect::<Vec<_>>()
    );

    // simulate: the same files, and run.json records the settings.
    let sim = |out: &str, config: &str, sets: bool| {
        let mut args = vec!["-q", "simulate", config, "--steps", "30", "--out", out];
        if sets {
            args.extend(SETS);
        }
        run_ok_in(dir, &args);
    };
    sim("by_hand", edited, false);
    sim("set", shipped, true);
    for file in ["truth.csv", "measurements.csv", "inputs.csv"] {
        assert!(
            std::fs::read(dir.join("by_hand").join(file)).unwrap()
                == std::fs::read(dir.join("set").join(file)).unwrap(),
            "{file}"
        );
    }
    let record = json(&dir.join("set/run.json"));
    assert_eq!(record["settings"], serde_json::json!([SETS[1], SETS[3]]));
    assert_eq!(record["config"]["dropout"]["p"], 0.6);
    assert!(
        json(&dir.join("by_hand/run.json"))
            .get("settings")
            .is_none()
    );

    // estimate: after simulate with --set, a bare estimate uses the settings; with --config
    // and --set, the estimates of the edited file; the metadata records the settings.
    let estimate = |out: &str, extra: &[&str]| {
        let mut args = vec![
            "-q",
            "estimate",
            "--meas",
            "by_hand/measurements.csv",
            "--inputs",
            "by_hand/inputs.csv",
            "--out",
            out,
        ];
        args.extend(extra);
        run_ok_in(dir, &args);
        json(&dir.join(out))
    };
    let by_hand = estimate("by_hand.json", &["--config", edited]);
    let set = estimate("set.json", &with_sets(&["--config", shipped]));
    let bare = run_ok_in(
        dir,
        &[
            "-q",
            "estimate",
            "--meas",
            "set/measurements.csv",
            "--format",
            "json",
        ],
    );
    let bare: serde_json::Value = serde_json::from_slice(&bare.stdout).unwrap();
    for other in [&set, &bare] {
        assert_eq!(by_hand["estimates"], other["estimates"]);
        assert_eq!(by_hand["summary"], other["summary"]);
    }
    assert_eq!(
        set["config"]["settings"],
        serde_json::json!([SETS[1], SETS[3]])
    );
    assert_eq!(bare["config"]["settings"], set["config"]["settings"]);
    assert!(by_hand["config"].get("settings").is_none());

    // evaluate: the same table but for the line that names the config.
    let evaluate = |config: &str, sets: bool| {
        let mut args = vec!["-q", "evaluate", config, "--runs", "2", "--filters"];
        args.push("distributed,joint");
        if sets {
            args.extend(SETS);
        }
        let out = String::from_utf8(run_ok_in(dir, &args).stdout).unwrap();
        out.lines()
            .skip(1)
            .map(|l| l.split_whitespace().take(7).collect::<Vec<_>>().join(" "))
            .collect::<Vec<_>>()
    };
    assert_eq!(evaluate(edited, false), evaluate(shipped, true));

    // plot series: the same figure from the edited file and from --set.
    let plot = |out: &str, extra: &[&str]| {
        let mut args = vec![
            "plot",
            "series",
            "--estimates",
            "by_hand.json",
            "--meas",
            "by_hand/measurements.csv",
            "--subsystem",
            "2",
            "--state",
            "1",
            "--out",
            out,
        ];
        args.extend(extra);
        run_ok_in(dir, &args);
        std::fs::read(dir.join(out)).unwrap()
    };
    assert!(
        plot("by_hand.svg", &["--config", edited])
            == plot("set.svg", &with_sets(&["--config", shipped]))
    );
}

/// A bad key, a value of the wrong type, a value the model refuses and a value that is not
/// TOML: exit 2, one line naming the config, the key and `--set`.
#[test]
fn a_bad_setting_names_its_key_and_says_it_came_from_set() {
    let shipped = shipped_config("platoon.toml");
    for (setting, says) in [
        ("dropout.q=0.7", "dropout.q (from --set): unknown field `q`"),
        (
            "model.M=\"large\"",
            "model.M (from --set): expected a matrix as a list of rows of numbers",
        ),
        (
            "model.M=[[0.02]]",
            "model.M (from --set): expected 2 × 2 (q × q), found 1 × 1",
        ),
        (
            "dropout.p=1.5",
            "dropout.p (from --set): expected a probability in [0, 1], found 1.5",
        ),
        (
            "model.Q=[[1, 0]",
            "model.Q (from --set): `[[1, 0]` is not a TOML value",
        ),
        (
            "override[2].p=0.5",
            "override[2].p (from --set): `override` has 0 tables, not 2",
        ),
    ] {
        for command in [&["check"][..], &["simulate", "--out", "unused"][..]] {
            let out = sisfilt()
                .arg(command[0])
                .arg(&shipped)
                .args(&command[1..])
                .args(["--set", setting])
                .output()
                .unwrap();
            assert_eq!(out.status.code(), Some(2), "{setting}");
            let msg = one_error_line(&out.stderr);
            assert!(
                msg.contains(&format!("platoon.toml: {says}")),
                "{setting}: {msg}"
            );
        }
    }
    let out = sisfilt()
        .arg("check")
        .arg(&shipped)
        .args(["--set", "dropout.p"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(one_error_line(&out.stderr).contains("expected KEY=VALUE"));
}
