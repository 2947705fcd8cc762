//! Studies cut into shards (docs/theory.md §11): a [`Shard`] names a block of a study's runs,
//! [`evaluate_part`] runs it and keeps the sums behind every figure ([`Part`]), and [`merge`]
//! adds the parts in shard order into the figures of the whole study ([`Study`]).

use std::ops::Range;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::{
    Compared, EvaluateError, EvaluateOptions, Evaluation, StudySums, Sweep, check_sweep,
    checked_steps, evaluation, run_inputs, tally,
};
use crate::error::Result;
use crate::inputs::RunInputs;
use crate::model::Model;

/// Parts that do not add up to one study ([`merge`]); each names the parts by the names the
/// caller gave them (their files).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    #[error("no parts to merge")]
    NoParts,
    #[error("{part}: not a part of the same study as {first}: {what}")]
    Foreign {
        part: String,
        first: String,
        what: String,
    },
    /// Its shard, runs and sums do not go together (a file edited by hand, or damaged).
    #[error("{part}: not a part written by `evaluate --shard`: {what}")]
    NotAPart { part: String, what: String },
    #[error("{part} and {other} are both shard {shard}")]
    Duplicate {
        part: String,
        other: String,
        shard: Shard,
    },
    /// `shards` lists the first few that are missing, and how many more.
    #[error("missing from the study: {shards} (given: {given})")]
    Missing { shards: String, given: String },
}

/// Which of a study's `R` runs a part holds: shard `index` of `count` (from 0), the runs
/// `⌊index·R/count⌋ ..= ⌊(index+1)·R/count⌋ − 1`, with the seeds the whole study gives them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    /// The whole study as one part.
    pub const WHOLE: Shard = Shard { index: 0, count: 1 };

    pub fn new(index: usize, count: usize) -> Result<Shard, EvaluateError> {
        if index < count {
            Ok(Shard { index, count })
        } else {
            Err(EvaluateError::Shard { index, count })
        }
    }

    /// Its runs (0-based) among `total`.
    pub fn runs(self, total: usize) -> Range<usize> {
        let at = |k: usize| (k as u128 * total as u128 / self.count as u128) as usize;
        at(self.index)..at(self.index + 1)
    }
}

/// `K/M`, as `--shard` takes it.
impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// One shard of a study: the JSON of `evaluate --shard K/M --out`, which [`merge`] adds up.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Part {
    pub sisfilt_version: String,
    pub config: String,
    /// SHA-256 of the model as read (every matrix, `p`, the initial conditions, the inputs of
    /// the runs; not the config's name): the parts of one study share it.
    pub model_sha256: String,
    pub options: EvaluateOptions,
    /// The arrival probabilities of `--sweep-p`, or `None` for one evaluation.
    pub sweep_p: Option<Vec<f64>>,
    pub shard: Shard,
    /// Its runs, from the first to one past the last (0-based).
    pub runs: [usize; 2],
    pub subsystems: usize,
    /// The state size `n` of each subsystem.
    pub n: usize,
    pub steps: usize,
    /// One per value of `sweep_p`, or one.
    pub studies: Vec<StudySums>,
    /// Time of the part (seconds).
    pub wall_time_s: f64,
}

/// SHA-256 of what decides a study's figures besides its options: the model (its name
/// aside) and the inputs `u` of its runs.
fn model_digest(model: &Model, u: &[Vec<f64>]) -> String {
    use sha2::Digest;
    let mut unnamed = model.clone();
    unnamed.name.clear();
    let mut digest = sha2::Sha256::new();
    // Debug shows every number with the digits that read back to it.
    digest.update(format!("{:?}", *unnamed).as_bytes());
    for v in u.iter().flatten() {
        digest.update(v.to_le_bytes());
    }
    digest
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Runs shard `shard` of the study that [`evaluate`](super::evaluate) (or with `sweep`,
/// [`sweep_p`](super::sweep_p)) runs in whole, and keeps its sums; `tick` is called once per
/// finished run.
pub fn evaluate_part(
    model: &Model,
    inputs: &RunInputs,
    config: &str,
    opts: EvaluateOptions,
    sweep: Option<&[f64]>,
    shard: Shard,
    tick: impl Fn() -> Result<()> + Sync,
) -> Result<Part> {
    let start = Instant::now();
    let steps = checked_steps(model, &opts)?;
    sweep.map(check_sweep).transpose()?;
    if shard.count > opts.runs {
        return Err(EvaluateError::MoreShardsThanRuns {
            count: shard.count,
            runs: opts.runs,
        }
        .into());
    }
    let runs = shard.runs(opts.runs);
    let u = run_inputs(model, inputs, steps)?;
    let studies = match sweep {
        None => vec![tally(model, inputs, &opts, steps, &u, runs.clone(), &tick)?],
        Some(values) => values
            .iter()
            .map(|&p| {
                let model = model.with_arrival_probability(p);
                tally(&model, inputs, &opts, steps, &u, runs.clone(), &tick)
            })
            .collect::<Result<_>>()?,
    };
    Ok(Part {
        sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
        config: config.to_string(),
        model_sha256: model_digest(model, &u),
        options: opts,
        sweep_p: sweep.map(<[f64]>::to_vec),
        shard,
        runs: [runs.start, runs.end],
        subsystems: model.subsystems,
        n: model.dims.n,
        steps,
        studies,
        wall_time_s: start.elapsed().as_secs_f64(),
    })
}

/// A whole study: what `evaluate` writes, or with `--sweep-p` what `evaluate --sweep-p`
/// writes.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Study {
    Sweep(Sweep),
    Evaluation(Evaluation),
}

impl Study {
    /// The table printed on standard output.
    pub fn table(&self) -> String {
        match self {
            Study::Sweep(s) => s.table(),
            Study::Evaluation(e) => e.table(),
        }
    }
}

/// Adds up the parts of one study, each with the name its errors call it by (its file), in
/// shard order, into the figures of the whole study. Refused: parts of different models,
/// options or versions, two parts of one shard, a shard missing. The wall times are the
/// parts' summed.
pub fn merge(parts: &[(String, Part)]) -> Result<Study, MergeError> {
    let (first_name, first) = parts.first().ok_or(MergeError::NoParts)?;
    let foreign = |name: &str, what: String| MergeError::Foreign {
        part: name.to_string(),
        first: first_name.clone(),
        what,
    };
    let mut by_shard: std::collections::BTreeMap<usize, (&String, &Part)> = Default::default();
    for (name, part) in parts {
        let differ = |what: &str, a: &dyn std::fmt::Debug, b: &dyn std::fmt::Debug| {
            foreign(name, format!("{what} differ ({a:?} and {b:?})"))
        };
        if part.sisfilt_version != first.sisfilt_version {
            return Err(differ(
                "sisfilt versions",
                &part.sisfilt_version,
                &first.sisfilt_version,
            ));
        }
        if part.model_sha256 != first.model_sha256 {
            return Err(foreign(
                name,
                "the models differ (config, --set values or inputs)".into(),
            ));
        }
        if part.options != first.options {
            return Err(foreign(
                name,
                option_difference(&part.options, &first.options),
            ));
        }
        if part.sweep_p != first.sweep_p {
            return Err(differ("--sweep-p values", &part.sweep_p, &first.sweep_p));
        }
        if part.shard.count != first.shard.count {
            return Err(differ(
                "shard counts",
                &part.shard.count,
                &first.shard.count,
            ));
        }
        let checked = Shard::new(part.shard.index, part.shard.count)
            .ok()
            .filter(|s| {
                s.runs(part.options.runs) == (part.runs[0]..part.runs[1])
                    && part.studies.len() == first.studies.len()
                    && part.studies.iter().zip(&first.studies).all(|(a, b)| {
                        names(a) == names(b)
                            && a.filters.iter().all(|f| {
                                f.scores.accuracy.is_of(first.n)
                                    && f.scores.per_step.is_of(first.steps)
                            })
                    })
            })
            .ok_or_else(|| MergeError::NotAPart {
                part: name.clone(),
                what: "its shard, runs and sums do not go together".into(),
            })?;
        if let Some((other, _)) = by_shard.insert(checked.index, (name, part)) {
            return Err(MergeError::Duplicate {
                part: name.clone(),
                other: other.clone(),
                shard: checked,
            });
        }
    }
    let count = first.shard.count;
    if by_shard.len() < count {
        // The count may be far larger than the parts given: name the first few missing.
        const NAMED: usize = 5;
        let mut shards: Vec<String> = (0..count)
            .filter(|k| !by_shard.contains_key(k))
            .take(NAMED)
            .map(|k| format!("shard {k}/{count}"))
            .collect();
        let more = count - by_shard.len() - shards.len();
        if more > 0 {
            shards.push(format!("and {more} more"));
        }
        let given: Vec<String> = parts.iter().map(|(name, _)| name.clone()).collect();
        return Err(MergeError::Missing {
            shards: shards.join(", "),
            given: given.join(", "),
        });
    }
    let mut in_order = by_shard.into_values().map(|(_, part)| part);
    let mut sums = in_order.next().expect("one part at least").studies.clone();
    for part in in_order {
        for (study, later) in sums.iter_mut().zip(&part.studies) {
            study.add(later);
        }
    }
    let figures = |sums: StudySums| {
        evaluation(
            &first.config,
            first.subsystems,
            first.steps,
            first.options.clone(),
            sums,
        )
    };
    Ok(match &first.sweep_p {
        None => Study::Evaluation(figures(sums.remove(0))),
        Some(values) => {
            let total_wall_time_s = sums.iter().map(|s| s.wall_time_s).sum();
            Study::Sweep(Sweep {
                sisfilt_version: first.sisfilt_version.clone(),
                config: first.config.clone(),
                options: first.options.clone(),
                subsystems: first.subsystems,
                steps: first.steps,
                sweep_p: values.clone(),
                evaluations: sums.into_iter().map(figures).collect(),
                total_wall_time_s,
            })
        }
    })
}

/// The first option in which `options` differ from `first`'s, in words.
fn option_difference(options: &EvaluateOptions, first: &EvaluateOptions) -> String {
    let (serde_json::Value::Object(a), serde_json::Value::Object(b)) = (
        serde_json::to_value(options).expect("options serialise"),
        serde_json::to_value(first).expect("options serialise"),
    ) else {
        unreachable!("options serialise as a map")
    };
    a.iter()
        .find(|(key, value)| b.get(*key) != Some(value))
        .map_or_else(
            || "the options differ".into(),
            |(key, value)| {
                let theirs = b.get(key).unwrap_or(&serde_json::Value::Null);
                format!("the options differ: {key} {value} against {theirs}")
            },
        )
}

/// The filters of a part's study, in order.
fn names(sums: &StudySums) -> Vec<Compared> {
    sums.filters.iter().map(|f| f.name).collect()
}
