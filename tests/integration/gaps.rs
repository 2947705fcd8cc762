//! Gaps: values missing from the measurement file (docs/theory.md §15). A row not in the data
//! is deleted from that step's measurement equation in both dropout modes, so every filter,
//! update and smoother is checked against independent ways of deleting it: a model without
//! that row, a model whose subsystem has `p = 0` where it has no row (nothing to update with),
//! and a dense lifted Nahi filter written here that deletes the rows.

use nalgebra::{DMatrix, DVector};
use sisfilt::filter::{CentralizedFilter, ChainFilter, Dropouts, FilterKind, Update};
use sisfilt::model::Model;
use sisfilt::run::{Estimates, RunSpec, estimate};

use crate::common::{
    Csv, model_from, platoon_with_gaps, shipped_config, simulate_run, sisfilt, write_file,
};
use crate::reference_filters::{CHAIN, assert_filtered_equal, dense_lifted, dense_predict};

/// [`CHAIN`] with every subsystem alike (one `p`, no override), so that the distributed
/// filter with the paper's moment shares one gain (until a gap).
fn homogeneous_chain() -> String {
    let text = CHAIN.replace("p = [0.9, 0.6, 0.8, 0.7]", "p = 0.7");
    text[..text.find("[[override]]").unwrap()].to_string()
}

/// The same model with only the first measured element: `J`, `M` and `R` lose row 2.
fn first_row_only(text: &str) -> String {
    text.replace("J = [[1.0, 0.0], [0.3, 1.0]]", "J = [[1.0, 0.0]]")
        .replace("R = [[0.1], [0.0]]", "R = [[0.1]]")
        .replace("M = [[0.2, 0.05], [0.05, 0.3]]", "M = [[0.2]]")
}

/// Every filter, update, dropout mode and smoothing that `estimate` runs.
fn specs() -> Vec<RunSpec> {
    let mut out = Vec::new();
    for filter in [
        FilterKind::Distributed,
        FilterKind::Joint,
        FilterKind::Centralized,
    ] {
        for (update, dropouts) in [
            (Update::Linear, Dropouts::Unknown),
            (Update::Mixture, Dropouts::Unknown),
            (Update::Linear, Dropouts::Known),
        ] {
            for smooth in [false, true] {
                let base = RunSpec {
                    filter,
                    update,
                    dropouts,
                    smooth,
                    ..RunSpec::default()
                };
                if filter == FilterKind::Distributed && update == Update::Linear {
                    // The paper's preset: the shared gain on the homogeneous chain.
                    out.push(RunSpec {
                        paper: true,
                        ..base.clone()
                    });
                }
                out.push(base);
            }
        }
    }
    out
}

fn run(model: &Model, spec: &RunSpec, y: &[f64], u: &[f64]) -> Estimates {
    estimate(model, &spec.check().unwrap(), y, Some(u), None)
        .unwrap_or_else(|e| panic!("{spec:?}: {e}"))
}

/// `a` and `b` agree to 1e−10 relative to the larger (or both are NaN).
fn assert_values(a: &[f64], b: &[f64], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    for (k, (x, y)) in a.iter().zip(b).enumerate() {
        let close = (x - y).abs() <= 1e-10 * x.abs().max(y.abs()).max(1.0);
        assert!(close || x.is_nan() && y.is_nan(), "{what}[{k}]: {x} vs {y}");
    }
}

/// Two runs give the same estimates, covariances, NIS, `π` and log-likelihood (1e−10).
fn assert_same_estimates(a: &Estimates, b: &Estimates, what: &str) {
    assert_values(&a.x, &b.x, &format!("x of {what}"));
    assert_values(&a.p, &b.p, &format!("P of {what}"));
    assert_values(&a.nis, &b.nis, &format!("NIS of {what}"));
    assert_eq!(a.arrival.is_some(), b.arrival.is_some(), "{what}");
    if let (Some(pa), Some(pb)) = (&a.arrival, &b.arrival) {
        assert_values(pa, pb, &format!("π of {what}"));
    }
    let (la, lb) = (a.report.summary.loglik, b.report.summary.loglik);
    assert_eq!(la.is_some(), lb.is_some(), "{what}");
    if let (Some(la), Some(lb)) = (la, lb) {
        assert_values(&[la], &[lb], &format!("loglik of {what}"));
    }
}

/// An element missing at every step is the model without that row: the same estimates,
/// covariances, `π`, log-likelihood and NIS from every filter, update and smoother, in both
/// dropout modes.
#[test]
fn an_element_missing_everywhere_equals_the_model_without_its_row() {
    for text in [CHAIN.to_string(), homogeneous_chain()] {
        let (full, reduced) = (model_from(&text), model_from(&first_row_only(&text)));
        let sim = simulate_run(&full, 17);
        let u: Vec<f64> = sim.u.concat();
        let y_gap: Vec<f64> = sim
            .y
            .concat()
            .iter()
            .enumerate()
            .map(|(k, &v)| if k % 2 == 1 { f64::NAN } else { v })
            .collect();
        let y_reduced: Vec<f64> = y_gap.iter().copied().step_by(2).collect();
        for spec in specs() {
            let (a, b) = (
                run(&full, &spec, &y_gap, &u),
                run(&reduced, &spec, &y_reduced, &u),
            );
            assert_same_estimates(&a, &b, &format!("{spec:?}"));
        }
    }
}

/// A subsystem with no row in the data is only predicted: the same estimates and covariances
/// as a model whose arrival probability is 0 there (nothing arrives, so nothing updates), from
/// every unknown-dropout filter, update and smoother; its `π` is unknown (NaN) and its NIS
/// is not scored.
#[test]
fn a_subsystem_without_data_is_only_predicted() {
    let text = homogeneous_chain();
    let gapped = model_from(&text);
    let silent = model_from(&format!(
        "{text}\n[[override]]\nsubsystems = [3, 3]\nsteps = [8, 12]\np = 0.0\n"
    ));
    let sim = simulate_run(&gapped, 23);
    let (q, big_n) = (2, 4);
    let u: Vec<f64> = sim.u.concat();
    let in_gap = |k: usize| (7..12).contains(&(k / (big_n * q))) && k / q % big_n == 2;
    let y: Vec<f64> = sim.y.concat();
    let y_gap: Vec<f64> = y
        .iter()
        .enumerate()
        .map(|(k, &v)| if in_gap(k) { f64::NAN } else { v })
        .collect();
    for spec in specs()
        .into_iter()
        .filter(|s| s.dropouts == Dropouts::Unknown)
    {
        let what = format!("{spec:?}");
        let (a, b) = (run(&gapped, &spec, &y_gap, &u), run(&silent, &spec, &y, &u));
        assert_values(&a.x, &b.x, &format!("x of {what}"));
        assert_values(&a.p, &b.p, &format!("P of {what}"));
        for (cell, nis) in a.nis.iter().enumerate() {
            assert_eq!(nis.is_nan(), in_gap(cell * q), "NIS of {what} at {cell}");
        }
        if let (Some(pa), Some(pb)) = (&a.arrival, &b.arrival) {
            for (cell, (pa, pb)) in pa.iter().zip(pb).enumerate() {
                if in_gap(cell * q) {
                    assert!(pa.is_nan() && *pb == 0.0, "π of {what} at {cell}");
                } else {
                    assert_values(&[*pa], &[*pb], &format!("π of {what} at {cell}"));
                }
            }
        }
    }
}

/// The exact lifted moments `E[x xᵀ]`'s diagonal blocks at `t`, from the mean `m` and
/// covariance `c` of the lifted state (dense, written here).
fn second_moment_block(m: &DVector<f64>, c: &DMatrix<f64>, i: usize, n: usize) -> DMatrix<f64> {
    let mi = m.rows(i * n, n);
    c.view((i * n, i * n), (n, n)) + mi * mi.transpose()
}

/// The centralized filter with unknown dropouts on measurements whose gaps change from step
/// to step (none, one element, a whole subsystem) equals Nahi's update of the dense lifted
/// system built here on the received rows: `H = p_i J_r`, `R = M_rr + p_i (1 − p_i) J_r S_ii
/// J_rᵀ` with the exact second moments, the rows not in the data deleted.
#[test]
fn centralized_nahi_filter_with_gaps_equals_the_dense_filter_on_the_received_rows() {
    let model = model_from(CHAIN);
    let sim = simulate_run(&model, 31);
    let (n, q, big_n) = (2, 2, 4);
    let size = big_n * n;
    let mut cent = CentralizedFilter::new(&model, false, 100).unwrap();
    let m0 = DVector::from_fn(size, |r, _| [1.0, -0.5][r % n]);
    let mut p0 = DMatrix::zeros(size, size);
    for i in 0..big_n {
        p0.view_mut((i * n, i * n), (n, n))
            .copy_from(&DMatrix::from_row_slice(2, 2, &[0.8, 0.1, 0.1, 0.6]));
    }
    let (mut x, mut p) = (m0.clone(), p0.clone());
    let (mut mean, mut cov) = (m0, p0);
    let mut gaps = 0;
    for (t0, y) in sim.y.iter().enumerate() {
        let t = t0 + 1;
        let y: Vec<f64> = y
            .iter()
            .enumerate()
            .map(|(k, &v)| {
                let gap = (t + k / q) % 6 == 0 || (k * 5 + t) % 4 == 0;
                if gap { f64::NAN } else { v }
            })
            .collect();
        gaps += y.iter().filter(|v| v.is_nan()).count();
        let u = &sim.u[t0];
        cent.step(&y, u).unwrap();
        let obs: Vec<usize> = (0..y.len()).filter(|&k| !y[k].is_nan()).collect();
        let prob = |k: usize| model.window(t).p[k / q];
        let h = DMatrix::from_fn(obs.len(), size, |r, c| {
            let k = obs[r];
            if c / n == k / q {
                prob(k) * model.params(t, k / q + 1).J[(k % q, c % n)]
            } else {
                0.0
            }
        });
        let reff = DMatrix::from_fn(obs.len(), obs.len(), |r, c| {
            let (a, b) = (obs[r], obs[c]);
            if a / q != b / q {
                return 0.0;
            }
            let i = a / q;
            let prm = model.params(t, i + 1);
            let s = second_moment_block(&mean, &cov, i, n);
            let jsj = &prm.J * s * prm.J.transpose();
            prm.M[(a % q, b % q)] + prob(a) * (1.0 - prob(a)) * jsj[(a % q, b % q)]
        });
        let innov = DVector::from_fn(obs.len(), |r, _| {
            let k = obs[r];
            y[k] - model.params(t, k / q + 1).R[(k % q, 0)] * u[k / q]
        }) - &h * &x;
        if !obs.is_empty() {
            let sigma = &h * &p * h.transpose() + reff;
            let gain = &p * h.transpose() * sigma.try_inverse().unwrap();
            x = &x + &gain * innov;
            p = (DMatrix::identity(size, size) - &gain * &h) * &p;
        }
        assert_filtered_equal(t, cent.filtered(), &x, &p, n);
        dense_predict(&model, t, u, &mut x, &mut p);
        // The moments of the lifted state: X⁺ = A_eff X + U_eff U + Ω.
        let (a_eff, u_eff) = dense_lifted(&model, t);
        mean = &a_eff * &mean + &u_eff * DVector::from_column_slice(u);
        let mut next = &a_eff * &cov * a_eff.transpose();
        for i in 0..big_n {
            let mut block = next.view_mut((i * n, i * n), (n, n));
            block += &model.params(t, i + 1).Q;
        }
        cov = next;
    }
    assert!(gaps > 40, "the pattern deletes rows ({gaps})");
}

/// On the command line, the platoon's measurements with car 3 switched off for steps 5–9 and
/// the radar of car 5 (element 1) missing throughout: `estimate` with unknown dropouts and the
/// mixture update leaves `arrival` and `nis` empty where nothing was received, detection
/// scores only the measurements that are there, and `plot` reads the estimates with their
/// empty cells.
#[test]
fn gaps_on_the_command_line() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let config = shipped_config("platoon.toml");
    let silent = |t: usize, i: usize| i == 3 && (5..=9).contains(&t);
    let meas = platoon_with_gaps(dir, 12, "gaps.csv", |t, i| {
        [silent(t, i) || i == 5, silent(t, i)]
    });
    let estimates = dir.join("estimates.csv");
    let out = sisfilt()
        .args(["estimate", "--config"])
        .arg(&config)
        .arg("--meas")
        .arg(&meas)
        .arg("--inputs")
        .arg(dir.join("inputs.csv"))
        .arg("--truth")
        .arg(dir.join("truth.csv"))
        .args(["--filter", "joint", "--update", "mixture", "--nis", "--out"])
        .arg(&estimates)
        .assert()
        .success()
        .get_output()
        .clone();
    let stderr = String::from_utf8(out.stderr).unwrap();
    let rows = Csv::read(&estimates);
    let (arrival, nis) = (rows.header.len() - 2, rows.header.len() - 1);
    assert_eq!(rows.header[arrival], "arrival");
    let mut received_gamma = (0, 0);
    let truth = Csv::read(&dir.join("truth.csv"));
    for (row, truth_row) in rows.rows.iter().zip(&truth.rows) {
        let (t, i): (usize, usize) = (row[0].parse().unwrap(), row[1].parse().unwrap());
        assert_eq!(
            row[arrival].is_empty(),
            silent(t, i),
            "arrival at t={t} i={i}"
        );
        assert_eq!(row[nis].is_empty(), silent(t, i), "nis at t={t} i={i}");
        assert!(row[2..arrival].iter().all(|c| !c.is_empty()));
        if !silent(t, i) {
            let gamma = truth_row.last().unwrap();
            match gamma.as_str() {
                "0" => received_gamma.0 += 1,
                _ => received_gamma.1 += 1,
            }
        }
    }
    // Detection counts the scored measurements only: 12 · 20 − 5 of them.
    let (lost, received) = received_gamma;
    assert!(
        stderr.contains(&format!("of {lost} lost measurements detected"))
            && stderr.contains(&format!("among {received} received")),
        "{stderr}"
    );
    assert_eq!(lost + received, 12 * 20 - 5);
    let plot = |args: &[&str]| {
        sisfilt()
            .current_dir(dir)
            .arg("plot")
            .args(args)
            .arg("--estimates")
            .arg(&estimates)
            .assert()
            .success();
    };
    plot(&["heatmap", "--out", "map.svg"]);
    let (meas, config) = (meas.to_str().unwrap(), config.to_str().unwrap());
    plot(&[
        "series",
        "--meas",
        meas,
        "--config",
        config,
        "--subsystem",
        "3",
        "--state",
        "1",
        "--out",
        "car3.svg",
    ]);
}

/// Subsystems without a sensor (`measured = false`): `simulate` leaves their cells empty and
/// draws everything else as it would with a sensor there; every filter takes them as gaps, so
/// a run of that model on complete data equals a run of the model with sensors on data with
/// those cells empty — estimates, covariances and the log-likelihood (which their noise no
/// longer enters) — and `evaluate` replays its covariance passes with them.
#[test]
fn subsystems_without_a_sensor_are_gaps() {
    let unmeasured = |t: usize, i: usize| (i == 2 || i == 4) && (5..=12).contains(&t) || i == 1;
    let without = format!(
        "{}\n[[override]]\nsubsystems = [[2, 2], [4, 4]]\nsteps = [5, 12]\nmeasured = false\n\n[[override]]\nsubsystems = [1, 1]\nmeasured = false\n",
        homogeneous_chain()
    );
    let (with_model, without_model) = (model_from(&homogeneous_chain()), model_from(&without));
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let config = write_file(dir, "without.toml", &without);
    let with_config = write_file(dir, "with.toml", &homogeneous_chain());
    for (path, out) in [(&config, "without"), (&with_config, "with")] {
        sisfilt()
            .args(["-q", "simulate"])
            .arg(path)
            .args(["--out", out])
            .current_dir(dir)
            .assert()
            .success();
    }
    // check names them per window.
    let report = sisfilt().arg("check").arg(&config).output().unwrap();
    let report = String::from_utf8(report.stdout).unwrap();
    for line in [
        "t = 1..4: no sensor on subsystems 1 (their measurements are gaps)",
        "t = 5..12: no sensor on subsystems 1, 2, 4 (their measurements are gaps)",
        "t = 13..25: no sensor on subsystems 1 (their measurements are gaps)",
    ] {
        assert!(report.lines().any(|l| l == line), "{line}: {report}");
    }
    // The same draws: the cells of the subsystems with a sensor are the same, the others empty.
    let (a, b) = (
        Csv::read(&dir.join("without/measurements.csv")),
        Csv::read(&dir.join("with/measurements.csv")),
    );
    let (ta, tb) = (
        Csv::read(&dir.join("without/truth.csv")),
        Csv::read(&dir.join("with/truth.csv")),
    );
    for (k, (ra, rb)) in a.rows.iter().zip(&b.rows).enumerate() {
        let (t, i): (usize, usize) = (ra[0].parse().unwrap(), ra[1].parse().unwrap());
        if unmeasured(t, i) {
            assert!(ra[2..].iter().all(String::is_empty), "{ra:?}");
            assert_eq!(ta.rows[k].last().unwrap(), "0");
        } else {
            assert_eq!(ra, rb);
            assert_eq!(ta.rows[k], tb.rows[k]);
        }
    }
    // Filters: the model without sensors on complete data, the model with them on the data
    // with those cells empty.
    let sim = simulate_run(&with_model, 5);
    let u: Vec<f64> = sim.u.concat();
    let (q, big_n) = (2, 4);
    let y: Vec<f64> = sim.y.concat();
    let y_gap: Vec<f64> = y
        .iter()
        .enumerate()
        .map(|(k, &v)| {
            if unmeasured(k / (big_n * q) + 1, k / q % big_n + 1) {
                f64::NAN
            } else {
                v
            }
        })
        .collect();
    for spec in specs() {
        let (a, b) = (
            run(&without_model, &spec, &y, &u),
            run(&with_model, &spec, &y_gap, &u),
        );
        assert_same_estimates(&a, &b, &format!("{spec:?}"));
    }
    // evaluate: the replayed covariance passes (joint, centralized) take the missing sensors.
    sisfilt()
        .current_dir(dir)
        .args([
            "evaluate",
            "without.toml",
            "--runs",
            "2",
            "--out",
            "ev.json",
        ])
        .assert()
        .success();
    let ev: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("ev.json")).unwrap()).unwrap();
    for f in ev["filters"].as_array().unwrap() {
        assert!(f["skipped"].is_null(), "{}: {}", f["name"], f["skipped"]);
        assert!(
            f["accuracy"]["rmse_overall"].as_f64().unwrap().is_finite(),
            "{}",
            f["name"]
        );
    }
}

/// The gap pattern of the tests below: at step `t`, element `k` of the chain's `y` (`q = 2`)
/// is missing — whole subsystems at some steps, single elements at others, none at the rest.
fn changing_gap(t: usize, k: usize) -> bool {
    (t + k / 2).is_multiple_of(6) || (k * 5 + t).is_multiple_of(4)
}

fn with_changing_gaps(y: &[f64], t: usize) -> Vec<f64> {
    y.iter()
        .enumerate()
        .map(|(k, &v)| if changing_gap(t, k) { f64::NAN } else { v })
        .collect()
}

/// On a gap pattern that changes every step, the joint filter at full band (loading 0) is the
/// centralized filter — Nahi's update with the band and the lifted moment, and the mixture
/// update — which the dense reference above checks; so each deletes the rows as it does.
#[test]
fn joint_filter_at_full_band_deletes_the_rows_as_the_centralized_one() {
    use sisfilt::filter::{JointFilter, JointOptions, SecondMoment};
    let model = model_from(CHAIN);
    let sim = simulate_run(&model, 41);
    for (moment, update) in [
        (SecondMoment::Band, Update::Linear),
        (SecondMoment::Lifted, Update::Linear),
        (SecondMoment::Band, Update::Mixture),
    ] {
        let opts = JointOptions {
            loading: Some(0.0),
            update,
            ..JointOptions::full_band(&model, moment, Dropouts::Unknown)
        };
        let mut joint = JointFilter::new(&model, opts).unwrap();
        let cent = CentralizedFilter::new(&model, false, 100).unwrap();
        let mut cent = match update {
            Update::Mixture => cent.with_mixture_update().unwrap(),
            Update::Linear => cent,
        };
        for (t0, (y, u)) in sim.y.iter().zip(&sim.u).enumerate() {
            let y = with_changing_gaps(y, t0 + 1);
            joint.step(&y, u).unwrap();
            cent.step(&y, u).unwrap();
            let what = format!("{moment:?} {update:?} t = {}", t0 + 1);
            assert_values(joint.filtered().0, cent.filtered().0, &format!("x {what}"));
            assert_values(joint.filtered().1, cent.filtered().1, &format!("P {what}"));
            if let (Some(a), Some(b)) = (joint.arrival(), cent.arrival()) {
                assert_values(a, b, &format!("π {what}"));
            }
        }
    }
}

/// With one subsystem (no coupling) the distributed filter's mixture update on a changing gap
/// pattern equals the mixture update written here on the received rows alone (`J_r`, `M_rr`,
/// `R_r`: the rows deleted), followed by the prediction `A x + C u`, `A P Aᵀ + Q`; with no row
/// the prior stays and `π` is unknown.
#[test]
fn mixture_update_with_gaps_equals_the_update_on_the_received_rows() {
    let text = homogeneous_chain().replace("subsystems = 4", "subsystems = 1");
    let model = model_from(&text);
    let sim = simulate_run(&model, 43);
    let spec = RunSpec {
        update: Update::Mixture,
        ..RunSpec::default()
    };
    let mut filter = spec.check().unwrap().build_filter(&model).unwrap();
    let prm = model.params(1, 1).clone();
    let p_arrive = 0.7;
    let mut x = DVector::from_column_slice(&[1.0, -0.5]);
    let mut p = DMatrix::from_row_slice(2, 2, &[0.8, 0.1, 0.1, 0.6]);
    let log_normal = |e: &DVector<f64>, s: &DMatrix<f64>| {
        -0.5 * (e.len() as f64 * (2.0 * std::f64::consts::PI).ln()
            + s.determinant().ln()
            + (e.transpose() * s.clone().try_inverse().unwrap() * e)[0])
    };
    for (t0, (y, u)) in sim.y.iter().zip(&sim.u).enumerate() {
        let t = t0 + 1;
        let y = with_changing_gaps(y, t);
        filter.step(&y, u).unwrap();
        let rows: Vec<usize> = (0..2).filter(|&k| !y[k].is_nan()).collect();
        let pick = |m: &DMatrix<f64>, cols: bool| {
            DMatrix::from_fn(
                rows.len(),
                if cols { rows.len() } else { m.ncols() },
                |r, c| m[(rows[r], if cols { rows[c] } else { c })],
            )
        };
        let (j, m) = (pick(&prm.J, false), pick(&prm.M, true));
        let ru = &prm.R * DVector::from_column_slice(u);
        let e0 = DVector::from_fn(rows.len(), |r, _| y[rows[r]] - ru[rows[r]]);
        let pi = if rows.is_empty() {
            f64::NAN
        } else {
            let e = &e0 - &j * &x;
            let s1 = &j * &p * j.transpose() + &m;
            let (l1, l0) = (log_normal(&e, &s1), log_normal(&e0, &m));
            let pi = p_arrive * l1.exp() / (p_arrive * l1.exp() + (1.0 - p_arrive) * l0.exp());
            let k = &p * j.transpose() * s1.clone().try_inverse().unwrap();
            let g = &k * &e;
            p = &p - &k * &s1 * k.transpose() * pi + &g * g.transpose() * (pi * (1.0 - pi));
            x = &x + &g * pi;
            pi
        };
        let p_blocks: Vec<f64> = p.as_slice().to_vec();
        assert_values(filter.filtered().0, x.as_slice(), &format!("x t = {t}"));
        assert_values(filter.filtered().1, &p_blocks, &format!("P t = {t}"));
        assert_values(filter.arrival().unwrap(), &[pi], &format!("π t = {t}"));
        x = &prm.A * &x + &prm.C * DVector::from_column_slice(u);
        p = &prm.A * &p * prm.A.transpose() + &prm.Q;
    }
}
