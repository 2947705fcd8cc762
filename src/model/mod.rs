//! The validated model of docs/theory.md §1: dimensions, parameter sets and where they apply.
//!
//! [`Model::from_config`] checks every shape, value and range of a [`RawConfig`] once; the rest
//! of the crate relies on those checks and never re-validates. Parameters that vary in time or
//! space (`[[override]]`) are stored as a few distinct [`Params`] sets plus, per time window, the
//! set index of each subsystem: nothing is copied per `(t, i)`.
#![allow(non_snake_case)]

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::DMatrix;

use crate::config::{
    ConfigSetting, ConfigSource, InputKind, RawConfig, RawMatrix, RawOverride, RawProbability,
    RawRanges,
};
use crate::error::Result;

mod checker;
mod initial;
mod noise;

use checker::Checker;
pub use initial::{InitialCondition, InitialConditions};

/// The sizes of one subsystem (docs/theory.md §1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct Dims {
    /// State dimension `n`.
    pub n: usize,
    /// Input dimension `m` (0 when there is no input).
    pub m: usize,
    /// Measurement dimension `q`.
    pub q: usize,
    /// `n⁺ = dim v⁺ = dim w⁺`, the signal passed from `i` to `i+1`.
    pub plus: usize,
    /// `n⁻ = dim v⁻ = dim w⁻`, the signal passed from `i+1` to `i`.
    pub minus: usize,
}

impl Dims {
    /// `n⁺ + n⁻`, the length of `v` and `w`.
    pub fn s(&self) -> usize {
        self.plus + self.minus
    }
}

/// One set of subsystem parameters, (P1), (P2), (P5).
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    pub A: DMatrix<f64>,
    pub B: DMatrix<f64>,
    pub C: DMatrix<f64>,
    pub D: DMatrix<f64>,
    pub G: DMatrix<f64>,
    pub H: DMatrix<f64>,
    pub J: DMatrix<f64>,
    pub R: DMatrix<f64>,
    /// Measurement noise covariance, symmetric positive definite.
    pub M: DMatrix<f64>,
    /// Process noise covariance, symmetric positive semidefinite.
    pub Q: DMatrix<f64>,
}

/// The names of the matrices of [`Params`], in config order.
pub const MATRIX_KEYS: [&str; 10] = ["A", "B", "C", "D", "G", "H", "J", "R", "M", "Q"];

impl Params {
    /// The matrix named by a config key (one of [`MATRIX_KEYS`]).
    pub fn get(&self, key: &str) -> &DMatrix<f64> {
        match key {
            "A" => &self.A,
            "B" => &self.B,
            "C" => &self.C,
            "D" => &self.D,
            "G" => &self.G,
            "H" => &self.H,
            "J" => &self.J,
            "R" => &self.R,
            "M" => &self.M,
            "Q" => &self.Q,
            _ => unreachable!("not a matrix key: {key}"),
        }
    }

    fn get_mut(&mut self, key: &str) -> &mut DMatrix<f64> {
        match key {
            "A" => &mut self.A,
            "B" => &mut self.B,
            "C" => &mut self.C,
            "D" => &mut self.D,
            "G" => &mut self.G,
            "H" => &mut self.H,
            "J" => &mut self.J,
            "R" => &mut self.R,
            "M" => &mut self.M,
            "Q" => &mut self.Q,
            _ => unreachable!("not a matrix key: {key}"),
        }
    }
}

/// How `u(t,i)` is produced (docs/theory.md §13 `[input]`). Every element of `u` gets the same value.
#[derive(Debug, Clone, PartialEq)]
pub enum InputSpec {
    Zero,
    /// `u_k = amplitude`.
    Constant {
        amplitude: f64,
    },
    /// `u_k = amplitude · sin(2π t / period + phase · i)`.
    Sine {
        amplitude: f64,
        period: f64,
        phase: f64,
    },
    /// An inputs CSV (docs/theory.md §13), path already resolved against the config's folder.
    File(PathBuf),
}

impl InputSpec {
    /// The value of every element of a generated `u(t,i)`; `None` for [`InputSpec::File`].
    pub fn generated(&self, t: usize, i: usize) -> Option<f64> {
        match *self {
            InputSpec::Zero => Some(0.0),
            InputSpec::Constant { amplitude } => Some(amplitude),
            InputSpec::Sine {
                amplitude,
                period,
                phase,
            } => Some(
                amplitude
                    * (2.0 * std::f64::consts::PI * t as f64 / period + phase * i as f64).sin(),
            ),
            InputSpec::File(_) => None,
        }
    }
}

/// The parameters of all subsystems on a run of time steps `first..next window's first`.
#[derive(Debug, Clone, PartialEq)]
pub struct Window {
    /// First time step of the window (1-based).
    pub first: usize,
    /// For each subsystem (0-based), the index of its parameter set.
    pub ids: Vec<u32>,
    /// For each subsystem (0-based), the arrival probability `p(t,i)`.
    pub p: Vec<f64>,
    /// For each subsystem (0-based), whether it has a sensor (an override's `measured =
    /// false` says it has none: its measurements are gaps, docs/theory.md §15).
    pub measured: Vec<bool>,
}

impl Window {
    /// The runs of consecutive subsystems that share a parameter set, in chain order: their
    /// 0-based range and the set.
    pub fn runs(&self) -> impl Iterator<Item = (std::ops::Range<usize>, u32)> + '_ {
        self.ids.chunk_by(|a, b| a == b).scan(0, |first, run| {
            let start = *first;
            *first += run.len();
            Some((start..*first, run[0]))
        })
    }
}

/// The validated model, built once by [`Model::from_config`] (or [`Model::from_raw`]): a handle
/// to its [`ModelData`], which it shares. A clone costs a reference count, so a filter or a
/// smoother keeps a model of its own and borrows nothing, and a long-lived object in another
/// language can hold one. A change through the handle (`model.steps = …`) changes a copy of
/// the data when it is shared.
#[derive(Debug, Clone)]
pub struct Model(Arc<ModelData>);

impl std::ops::Deref for Model {
    type Target = ModelData;

    fn deref(&self) -> &ModelData {
        &self.0
    }
}

impl std::ops::DerefMut for Model {
    fn deref_mut(&mut self) -> &mut ModelData {
        Arc::make_mut(&mut self.0)
    }
}

/// The data of a [`Model`], read through it.
#[derive(Debug, Clone)]
pub struct ModelData {
    /// The config's name, for messages.
    pub name: String,
    pub dims: Dims,
    /// Chain length `N`.
    pub subsystems: usize,
    /// Horizon `T` of `simulate` and `evaluate` (the config's `steps`, which may be left out:
    /// `estimate` takes `T` from its data; see [`Model::horizon`]).
    pub steps: Option<usize>,
    /// Default seed.
    pub seed: u64,
    /// `x(1, i) ~ N(m0_i, P0_i)`.
    pub initial: InitialConditions,
    pub input: InputSpec,
    params: Vec<Params>,
    windows: Vec<Window>,
}

/// Largest chain length a config may ask for: every per-subsystem array is allocated up front,
/// so a mistyped `subsystems` must be refused rather than abort the process on allocation.
pub const MAX_SUBSYSTEMS: usize = 10_000_000;

/// Largest `N · k²`, `k` the largest of `n`, `q`, `m` and `n⁺ + n⁻`: the filters keep a few
/// `k × k` blocks per subsystem (covariances, second moments, the banded solve), allocated up
/// front, so a chain far too large for memory is refused here rather than aborting the process
/// on allocation (2²⁷ values are 1 GiB per such array).
pub const MAX_CHAIN_VALUES: usize = 1 << 27;

/// The expected shape of each matrix, as (rows, cols, description).
fn expected_shape(d: &Dims, key: &str) -> (usize, usize, &'static str) {
    let s = d.s();
    match key {
        "A" => (d.n, d.n, "n × n"),
        "B" => (d.n, s, "n × (plus+minus)"),
        "C" => (d.n, d.m, "n × m"),
        "D" => (s, d.n, "(plus+minus) × n"),
        "G" => (s, s, "(plus+minus) × (plus+minus)"),
        "H" => (s, d.m, "(plus+minus) × m"),
        "J" => (d.q, d.n, "q × n"),
        "R" => (d.q, d.m, "q × m"),
        "M" => (d.q, d.q, "q × q"),
        "Q" => (d.n, d.n, "n × n"),
        _ => unreachable!(),
    }
}

fn override_matrix<'a>(o: &'a RawOverride, key: &str) -> Option<&'a RawMatrix> {
    match key {
        "A" => o.A.as_ref(),
        "B" => o.B.as_ref(),
        "C" => o.C.as_ref(),
        "D" => o.D.as_ref(),
        "G" => o.G.as_ref(),
        "H" => o.H.as_ref(),
        "J" => o.J.as_ref(),
        "R" => o.R.as_ref(),
        "M" => o.M.as_ref(),
        "Q" => o.Q.as_ref(),
        _ => unreachable!(),
    }
}

/// A validated override: where it applies (inclusive ranges of steps and of subsystems; all
/// of them when `None`) and what it sets.
struct Override {
    subsystems: Option<Vec<(usize, usize)>>,
    steps: Option<Vec<(usize, usize)>>,
    matrices: Vec<(&'static str, DMatrix<f64>)>,
    p: Option<f64>,
    measured: Option<bool>,
}

impl Override {
    fn applies(&self, t: usize, i: usize) -> bool {
        let within = |ranges: &Option<Vec<(usize, usize)>>, x: usize| {
            ranges
                .as_ref()
                .is_none_or(|rs| rs.iter().any(|&(a, b)| a <= x && x <= b))
        };
        within(&self.steps, t) && within(&self.subsystems, i)
    }
}

impl Model {
    /// Reads, parses and checks the config file at `path` with `settings` over it (`--set`,
    /// [`ConfigSource::with_settings`]): the library's one way to load a config
    /// (docs/theory.md §13). Relative paths in it resolve against its folder.
    pub fn load(path: &Path, settings: &[ConfigSetting]) -> Result<Self> {
        Self::from_config(&ConfigSource::from_file(path)?.with_settings(settings)?)
    }

    /// Parses and checks config TOML held in memory; `name` names it in messages and relative
    /// paths in it (`input.path`) resolve against `dir`.
    pub fn from_toml_str(name: &str, dir: &Path, text: &str) -> Result<Self> {
        Self::from_config(&ConfigSource::from_text(
            name,
            dir.to_path_buf(),
            text.to_string(),
        )?)
    }

    /// Checks a config built in code and builds the model: the same tables as the TOML
    /// ([`RawConfig`]), the same validation and the same messages, which `name` opens; a
    /// relative `input.path` resolves against the working folder.
    pub fn from_raw(name: &str, raw: RawConfig) -> Result<Self> {
        Self::from_config(&ConfigSource::from_raw(name, PathBuf::from("."), raw)?)
    }

    /// Checks a parsed config and builds the model (docs/theory.md §1, §13).
    pub fn from_config(src: &ConfigSource) -> Result<Self> {
        let c = Checker {
            file: &src.name,
            settings: &src.settings,
        };
        let raw: &RawConfig = &src.raw;
        let subsystems = c.count("subsystems", raw.subsystems, 1)?;
        if subsystems > MAX_SUBSYSTEMS {
            return Err(c.err(
                "subsystems",
                format!("expected at most {MAX_SUBSYSTEMS} subsystems, found {subsystems}"),
            ));
        }
        let steps = raw.steps.map(|s| c.count("steps", s, 1)).transpose()?;
        let plus = c.count("interconnection.plus", raw.interconnection.plus, 0)?;
        let minus = c.count("interconnection.minus", raw.interconnection.minus, 0)?;

        let rm = &raw.model;
        let (n, n_cols) = c.shape("model.A", &rm.A)?;
        if n == 0 || n != n_cols {
            return Err(c.err(
                "model.A",
                format!("expected a square n × n matrix with n ≥ 1, found {n} × {n_cols}"),
            ));
        }
        let (q, _) = c.shape("model.J", &rm.J)?;
        if q == 0 {
            return Err(c.err("model.J", "expected at least one row (q ≥ 1)"));
        }
        let mut m = None;
        for (key, raw_m) in [("C", &rm.C), ("H", &rm.H), ("R", &rm.R)] {
            if let Some(raw_m) = raw_m {
                let (_, cols) = c.shape(&format!("model.{key}"), raw_m)?;
                match m {
                    None => m = Some((key, cols)),
                    Some((first, m0)) if m0 != cols => {
                        return Err(c.err(
                            &format!("model.{key}"),
                            format!("expected {m0} columns (m, from model.{first}), found {cols}"),
                        ));
                    }
                    _ => {}
                }
            }
        }
        let dims = Dims {
            n,
            m: m.map_or(0, |(_, m)| m),
            q,
            plus,
            minus,
        };
        let k = n.max(q).max(dims.m).max(dims.s());
        if subsystems.saturating_mul(k.saturating_mul(k)) > MAX_CHAIN_VALUES {
            return Err(c.err(
                "subsystems",
                format!(
                    "{subsystems} subsystems of size {k} need about {:.1e} bytes per covariance array: expected N · {k}² ≤ {MAX_CHAIN_VALUES}",
                    (subsystems as f64) * (k * k * 8) as f64
                ),
            ));
        }

        // B and D carry the coupling: left out, they are zero only where there is none.
        if dims.s() > 0 && subsystems > 1 {
            for (key, given) in [("B", rm.B.is_some()), ("D", rm.D.is_some())] {
                if !given {
                    return Err(c.err(
                        &format!("model.{key}"),
                        "required: the subsystems are coupled (interconnection.plus + minus > 0 and N > 1); only C, G, H, R and Q are zero when left out",
                    ));
                }
            }
        }
        let matrix = |key: &'static str, raw_m: Option<&RawMatrix>, prefix: &str| {
            let (r, cols, what) = expected_shape(&dims, key);
            match raw_m {
                Some(raw_m) => c.matrix(&format!("{prefix}{key}"), raw_m, r, cols, what),
                None => Ok(DMatrix::zeros(r, cols)),
            }
        };
        let base = Params {
            A: matrix("A", Some(&rm.A), "model.")?,
            B: matrix("B", rm.B.as_ref(), "model.")?,
            C: matrix("C", rm.C.as_ref(), "model.")?,
            D: matrix("D", rm.D.as_ref(), "model.")?,
            G: matrix("G", rm.G.as_ref(), "model.")?,
            H: matrix("H", rm.H.as_ref(), "model.")?,
            J: matrix("J", Some(&rm.J), "model.")?,
            R: matrix("R", rm.R.as_ref(), "model.")?,
            M: matrix("M", Some(&rm.M), "model.")?,
            Q: matrix("Q", rm.Q.as_ref(), "model.")?,
        };
        c.positive_definite("model.M", &base.M)?;
        c.positive_semidefinite("model.Q", &base.Q)?;

        let base_p = match &raw.dropout.p {
            RawProbability::All(p) => vec![c.probability("dropout.p", *p)?; subsystems],
            RawProbability::PerSubsystem(ps) => {
                if ps.len() != subsystems {
                    return Err(c.err(
                        "dropout.p",
                        format!(
                            "expected one value or a list of {subsystems} values (one per subsystem), found {}",
                            ps.len()
                        ),
                    ));
                }
                ps.iter()
                    .map(|&p| c.probability("dropout.p", p))
                    .collect::<Result<_>>()?
            }
        };

        let input = Self::input_spec(&c, src, dims.m)?;

        let mut overrides = Vec::with_capacity(raw.overrides.len());
        for (k, o) in raw.overrides.iter().enumerate() {
            let prefix = format!("override[{}].", k + 1);
            let mut matrices = Vec::new();
            for key in MATRIX_KEYS {
                if let Some(raw_m) = override_matrix(o, key) {
                    let mat = matrix(key, Some(raw_m), &prefix)?;
                    match key {
                        "M" => c.positive_definite(&format!("{prefix}M"), &mat)?,
                        "Q" => c.positive_semidefinite(&format!("{prefix}Q"), &mat)?,
                        _ => {}
                    }
                    matrices.push((key, mat));
                }
            }
            let ranges = |key: &str, raw: &Option<RawRanges>, max: Option<usize>| {
                raw.as_ref()
                    .map(|r| {
                        r.ranges()
                            .iter()
                            .map(|&r| c.range(&format!("{prefix}{key}"), r, max))
                            .collect::<Result<Vec<_>>>()
                    })
                    .transpose()
            };
            overrides.push(Override {
                subsystems: ranges("subsystems", &o.subsystems, Some(subsystems))?,
                steps: ranges("steps", &o.steps, None)?,
                matrices,
                p: o.p
                    .map(|p| c.probability(&format!("{prefix}p"), p))
                    .transpose()?,
                measured: o.measured,
            });
        }
        let initial = InitialConditions::from_raw(&c, raw, &overrides, n, subsystems)?;
        let (params, windows) = Self::build_windows(base, &base_p, &overrides, subsystems);

        Ok(Model(Arc::new(ModelData {
            name: src.name.clone(),
            dims,
            subsystems,
            steps,
            seed: raw.seed,
            initial,
            input,
            params,
            windows,
        })))
    }

    fn input_spec(c: &Checker, src: &ConfigSource, m: usize) -> Result<InputSpec> {
        let Some(inp) = &src.raw.input else {
            return Ok(InputSpec::Zero);
        };
        if m == 0 {
            return Err(c.err(
                "input",
                "the model has no input matrices (none of C, H, R is given, so m = 0): the [input] table would never be used; remove it, or give C, H or R",
            ));
        }
        let amplitude = c.finite("input.amplitude", inp.amplitude.unwrap_or(1.0))?;
        Ok(match inp.kind {
            InputKind::Zero => InputSpec::Zero,
            InputKind::Constant => InputSpec::Constant { amplitude },
            InputKind::Sine => {
                let period = inp
                    .period
                    .ok_or_else(|| c.err("input.period", "required for kind = \"sine\""))?;
                if !(period.is_finite() && period > 0.0) {
                    return Err(c.err(
                        "input.period",
                        format!("expected a finite number > 0, found {period}"),
                    ));
                }
                InputSpec::Sine {
                    amplitude,
                    period,
                    phase: c.finite("input.phase", inp.phase.unwrap_or(0.0))?,
                }
            }
            InputKind::File => {
                let path = inp
                    .path
                    .as_ref()
                    .ok_or_else(|| c.err("input.path", "required for kind = \"file\""))?;
                InputSpec::File(src.dir.join(path))
            }
        })
    }

    /// Splits time into windows on which every subsystem's parameters are constant, and
    /// builds one parameter set per distinct combination of matrix overrides.
    fn build_windows(
        base: Params,
        base_p: &[f64],
        overrides: &[Override],
        subsystems: usize,
    ) -> (Vec<Params>, Vec<Window>) {
        let mut starts = vec![1usize];
        for o in overrides {
            for &(a, b) in o.steps.iter().flatten() {
                starts.push(a);
                starts.push(b.saturating_add(1));
            }
        }
        starts.sort_unstable();
        starts.dedup();

        let mut params = vec![base];
        let mut set_of: HashMap<Vec<usize>, u32> = HashMap::from([(Vec::new(), 0)]);
        let mut windows: Vec<Window> = Vec::with_capacity(starts.len());
        for &first in &starts {
            let mut ids = Vec::with_capacity(subsystems);
            let mut p = Vec::with_capacity(subsystems);
            let mut measured = Vec::with_capacity(subsystems);
            for i in 1..=subsystems {
                let applied: Vec<usize> = (0..overrides.len())
                    .filter(|&k| overrides[k].applies(first, i))
                    .collect();
                measured.push(
                    applied
                        .iter()
                        .rev()
                        .find_map(|&k| overrides[k].measured)
                        .unwrap_or(true),
                );
                p.push(
                    applied
                        .iter()
                        .rev()
                        .find_map(|&k| overrides[k].p)
                        .unwrap_or(base_p[i - 1]),
                );
                let with_matrices: Vec<usize> = applied
                    .into_iter()
                    .filter(|&k| !overrides[k].matrices.is_empty())
                    .collect();
                let id = *set_of.entry(with_matrices).or_insert_with_key(|combo| {
                    let mut set = params[0].clone();
                    for &k in combo {
                        for (key, mat) in &overrides[k].matrices {
                            *set.get_mut(key) = mat.clone();
                        }
                    }
                    params.push(set);
                    (params.len() - 1) as u32
                });
                ids.push(id);
            }
            match windows.last() {
                Some(w) if w.ids == ids && w.p == p && w.measured == measured => {}
                _ => windows.push(Window {
                    first,
                    ids,
                    p,
                    measured,
                }),
            }
        }
        (params, windows)
    }

    /// The horizon `T` the config gives (`steps`), which `simulate` and `evaluate` need.
    pub fn horizon(&self) -> Result<usize> {
        self.steps.ok_or_else(|| crate::Error::Config {
            file: self.name.clone(),
            key: "steps".into(),
            msg: "not set: simulating needs the number of steps (add `steps = T` to the config; `simulate` also takes --steps)".into(),
        })
    }

    /// The index of the window holding time step `t` (1-based).
    pub fn window_index(&self, t: usize) -> usize {
        self.windows.partition_point(|w| w.first <= t) - 1
    }

    /// Sets the measurements `y(t, ·)` (`N·q` values) of the subsystems without a sensor at
    /// `t` to NaN: whatever a file holds there, no sensor measured it (docs/theory.md §15).
    pub fn blank_unmeasured(&self, t: usize, y: &mut [f64]) {
        let q = self.dims.q;
        for (i, _) in self
            .window(t)
            .measured
            .iter()
            .enumerate()
            .filter(|(_, m)| !**m)
        {
            y[i * q..(i + 1) * q].fill(f64::NAN);
        }
    }

    /// The window holding time step `t`.
    pub fn window(&self, t: usize) -> &Window {
        &self.windows[self.window_index(t)]
    }

    /// The parameter windows, in time order; the last one is open-ended.
    pub fn windows(&self) -> &[Window] {
        &self.windows
    }

    /// The index of the first window whose chain (every subsystem's parameter set) is that
    /// of window `k`: windows that differ only in `p` or in their sensors share the chain's
    /// interconnection and `A_eff`, so their figures.
    pub fn first_window_of_chain(&self, k: usize) -> usize {
        let ids = &self.windows[k].ids;
        self.windows[..k]
            .iter()
            .position(|earlier| &earlier.ids == ids)
            .unwrap_or(k)
    }

    /// The parameters of subsystem `i` (1-based) at time `t`.
    pub fn params(&self, t: usize, i: usize) -> &Params {
        &self.params[self.windows[self.window_index(t)].ids[i - 1] as usize]
    }

    /// The parameter set with index `id` (as found in [`Window::ids`]).
    pub fn param_set(&self, id: u32) -> &Params {
        &self.params[id as usize]
    }

    /// Every distinct parameter set.
    pub fn param_sets(&self) -> &[Params] {
        &self.params
    }

    /// The arrival probability `p(t,i)`.
    pub fn p(&self, t: usize, i: usize) -> f64 {
        self.windows[self.window_index(t)].p[i - 1]
    }

    /// The same model with the arrival probability `p` at every `(t, i)`: it replaces
    /// `[dropout] p` and every override's `p` (`evaluate --sweep-p`). `p` must lie in `[0, 1]`.
    pub fn with_arrival_probability(&self, p: f64) -> Model {
        debug_assert!((0.0..=1.0).contains(&p));
        let mut model = self.clone();
        for w in &mut model.windows {
            w.p.fill(p);
        }
        // Windows that differed only in p are one window now.
        model.windows.dedup_by(|later, earlier| {
            later.ids == earlier.ids && later.measured == earlier.measured
        });
        model
    }

    /// The same model with entry `(k, k)` of the matrix `key` (one of [`MATRIX_KEYS`]) at
    /// `value` in every parameter set: the configured matrix and every override's (`fit`,
    /// docs/theory.md §16).
    pub fn with_diagonal_entry(&self, key: &str, k: usize, value: f64) -> Model {
        let mut model = self.clone();
        for set in &mut model.params {
            set.get_mut(key)[(k, k)] = value;
        }
        model
    }

    /// Whether the two models give every subsystem the same parameters, arrival probability
    /// and sensor at every step, however their parameter sets are numbered.
    pub fn same_parameters(&self, other: &Model) -> bool {
        self.subsystems == other.subsystems
            && self.windows.len() == other.windows.len()
            && self.windows.iter().zip(&other.windows).all(|(a, b)| {
                a.first == b.first
                    && a.p == b.p
                    && a.measured == b.measured
                    && a.ids
                        .iter()
                        .zip(&b.ids)
                        .all(|(&x, &y)| self.params[x as usize] == other.params[y as usize])
            })
    }

    /// Whether a parameter (`A`…`Q` or `p`) varies in time and in space.
    pub fn variation(&self, key: &str) -> (bool, bool) {
        let (mut time, mut space) = (false, false);
        let value = |w: &Window, i: usize| -> Vec<f64> {
            if key == "p" {
                vec![w.p[i]]
            } else {
                self.params[w.ids[i] as usize].get(key).as_slice().to_vec()
            }
        };
        let w0 = &self.windows[0];
        for w in &self.windows {
            for i in 0..self.subsystems {
                let v = value(w, i);
                space |= v != value(w, 0);
                time |= v != value(w0, i);
            }
        }
        (time, space)
    }

    /// True when subsystems exchange signals at some time: `N > 1`, `n⁺ + n⁻ > 0`, and some
    /// `B` and `D` are non-zero.
    pub fn is_coupled(&self) -> bool {
        self.subsystems > 1
            && self.dims.s() > 0
            && self.params.iter().any(|p| p.B.amax() > 0.0)
            && self.params.iter().any(|p| p.D.amax() > 0.0)
    }

    /// True when a reading may be lost: `p(t, i) < 1` for some subsystem with a sensor. Only
    /// then does the unknown-dropout filter weigh the second moment `S` (its
    /// `R_eff = M + p(1−p) J S Jᵀ`, docs/theory.md §3, §4), and only then does the chain's
    /// stability concern it.
    pub fn loses_readings(&self) -> bool {
        self.windows
            .iter()
            .any(|w| w.p.iter().zip(&w.measured).any(|(&p, &m)| m && p < 1.0))
    }

    /// True when every process noise covariance `Q` is zero (the paper's setting).
    pub fn q_is_zero(&self) -> bool {
        self.params.iter().all(|p| p.Q.amax() == 0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_windows_runs_cover_the_chain_in_order() {
        let window = Window {
            first: 1,
            ids: vec![0, 0, 1, 1, 1, 0, 2],
            p: vec![1.0; 7],
            measured: vec![true; 7],
        };
        let runs: Vec<_> = window.runs().collect();
        assert_eq!(runs, [(0..2, 0), (2..5, 1), (5..6, 0), (6..7, 2)]);
        let empty = Window {
            ids: vec![],
            ..window
        };
        assert_eq!(empty.runs().count(), 0);
    }

    /// `Model::load` and `Model::from_toml_str` build the same model from the same text, and
    /// messages name the config as it was given.
    #[test]
    fn load_and_from_toml_str_agree() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/heat_rod.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let loaded = Model::load(&path, &[]).unwrap();
        let parsed = Model::from_toml_str("rod", path.parent().unwrap(), &text).unwrap();
        assert_eq!(loaded.dims, parsed.dims);
        assert_eq!(
            (loaded.subsystems, loaded.steps, loaded.seed),
            (parsed.subsystems, parsed.steps, parsed.seed)
        );
        assert_eq!(loaded.initial, parsed.initial);
        assert_eq!(loaded.name, path.display().to_string());
        assert_eq!(parsed.name, "rod");
        let err = Model::from_toml_str("inline", Path::new("."), "subsystems = 0").unwrap_err();
        assert!(err.to_string().starts_with("inline: "), "{err}");
        assert_eq!(err.exit_code(), 2);
    }
}
