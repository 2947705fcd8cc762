//! Configs as users write them (docs/theory.md §13): an override over several subsystems or
//! steps as a list of ranges, a `1 × 1` matrix as a number, and the matrices that are zero
//! when left out each give the model of the long form; a flat list that is not `[first, last]`
//! and a left-out coupling matrix are refused naming the key.

use sisfilt::model::Model;

use crate::common::{model_from, one_error_line, sisfilt, write_file};

const BASE: &str = "
subsystems = 25
steps = 30
[interconnection]
plus = 1
minus = 1
[model]
A = [[0.9]]
B = [[0.1, 0.05]]
D = [[0.5], [0.4]]
G = [[0.0, 0.0], [0.0, 0.0]]
J = [[1.0]]
M = [[0.05]]
Q = [[0.01]]
[dropout]
p = 0.8
[initial]
mean = [0.0]
cov = [[1.0]]
";

/// Every `(t, i)` of the two models has the same parameters and `p`.
fn assert_same_model(a: &Model, b: &Model, what: &str) {
    assert_eq!((a.subsystems, a.steps), (b.subsystems, b.steps), "{what}");
    for t in 1..=a.horizon().unwrap() + 1 {
        for i in 1..=a.subsystems {
            assert_eq!(a.params(t, i), b.params(t, i), "{what}: t = {t}, i = {i}");
            assert_eq!(a.window(t).p[i - 1], b.window(t).p[i - 1], "{what}: p");
        }
    }
}

#[test]
fn an_override_over_a_list_of_ranges_is_one_override_per_range() {
    let listed = model_from(&format!(
        "{BASE}[[override]]\nsubsystems = [[1, 1], [11, 11], [21, 23]]\nsteps = [[2, 4], [10, 10]]\np = 0.3\nQ = [[0.5]]\n"
    ));
    let mut spelled = BASE.to_string();
    for (s, t) in [
        ([1, 1], [2, 4]),
        ([11, 11], [2, 4]),
        ([21, 23], [2, 4]),
        ([1, 1], [10, 10]),
        ([11, 11], [10, 10]),
        ([21, 23], [10, 10]),
    ] {
        spelled += &format!(
            "[[override]]\nsubsystems = [{}, {}]\nsteps = [{}, {}]\np = 0.3\nQ = [[0.5]]\n",
            s[0], s[1], t[0], t[1]
        );
    }
    assert_same_model(&listed, &model_from(&spelled), "a list of ranges");
    // And it does change what it names, and nothing else.
    let base = model_from(BASE);
    assert_eq!(listed.window(3).p[10], 0.3);
    assert_eq!(listed.window(3).p[11], 0.8);
    assert_eq!(listed.window(5).p[0], 0.8);
    assert_eq!(base.window(3).p[10], 0.8);
}

#[test]
fn numbers_stand_for_one_by_one_matrices_and_left_out_matrices_are_zero() {
    let short = BASE
        .replace("A = [[0.9]]", "A = 0.9")
        .replace("J = [[1.0]]", "J = 1")
        .replace("M = [[0.05]]", "M = 0.05")
        .replace("Q = [[0.01]]", "Q = 0.01")
        .replace("cov = [[1.0]]", "cov = 1.0")
        .replace("G = [[0.0, 0.0], [0.0, 0.0]]\n", "");
    assert_same_model(&model_from(&short), &model_from(BASE), "numbers");
    // Without coupling, B and D may be left out too.
    let uncoupled = |text: &str| {
        text.replace("plus = 1", "plus = 0")
            .replace("minus = 1", "minus = 0")
    };
    let long = uncoupled(BASE)
        .replace("B = [[0.1, 0.05]]", "B = []")
        .replace("D = [[0.5], [0.4]]", "D = []")
        .replace("G = [[0.0, 0.0], [0.0, 0.0]]", "G = []");
    let bare = uncoupled(&short)
        .replace("B = [[0.1, 0.05]]\n", "")
        .replace("D = [[0.5], [0.4]]\n", "");
    assert_same_model(&model_from(&bare), &model_from(&long), "no coupling");
}

#[test]
fn misreadable_forms_are_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    for (text, says) in [
        (
            format!("{BASE}[[override]]\nsubsystems = [1, 11, 21]\np = 0.3\n"),
            "override[1].subsystems: expected [first, last], or a list of ranges",
        ),
        (
            format!("{BASE}[[override]]\nsteps = [1, 2, 3]\np = 0.3\n"),
            "override[1].steps: expected [first, last], or a list of ranges",
        ),
        (
            format!("{BASE}[[override]]\nsteps = [[1, 2], 3]\np = 0.3\n"),
            "found numbers and ranges mixed",
        ),
        (
            BASE.replace("B = [[0.1, 0.05]]\n", ""),
            "model.B: required: the subsystems are coupled",
        ),
        (
            BASE.replace("Q = [[0.01]]", "Q = \"small\""),
            "model.Q: expected a matrix as a list of rows of numbers",
        ),
    ] {
        let path = write_file(dir.path(), "c.toml", &text);
        let out = sisfilt().arg("check").arg(&path).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{says}");
        let msg = one_error_line(&out.stderr);
        assert!(msg.contains(says), "{says}: {msg}");
    }
}
