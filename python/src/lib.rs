//! The Python package `sisfilt`: a thin layer over the library's run API, numpy in and out.
//! Every computation is the library's (`sisfilt::run`, `sisfilt::fit`, `sisfilt::simulate`);
//! this file only converts arrays and options, and errors into Python exceptions:
//! `ValueError` for bad input (the command line's exit 2), `ArithmeticError` where the
//! numerics broke down (naming `t` and `i`), `RuntimeError` for anything else.

use numpy::ndarray::{ArrayD, IxDyn};
use numpy::{AllowTypeChange, IntoPyArray, PyArrayLikeDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyArithmeticError, PyMemoryError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PySlice};

use sisfilt::choice::Choice;
use sisfilt::config::{ConfigSetting, ConfigSource};
use sisfilt::filter::centralized::DEFAULT_MAX_LIFTED;
use sisfilt::fit::{FitSpec, ParamGroup};
use sisfilt::memory::{DEFAULT_MAX_MEMORY, human_bytes};
use sisfilt::run::RunSpec;

mod filter;
use filter::Filter;

/// A library error as the Python exception of its kind.
fn py_err(e: sisfilt::Error) -> PyErr {
    let numerical = match &e {
        sisfilt::Error::Numerical { .. } => true,
        sisfilt::Error::InRun { error, .. } => matches!(**error, sisfilt::Error::Numerical { .. }),
        _ => false,
    };
    if numerical {
        PyArithmeticError::new_err(e.to_string())
    } else if e.exit_code() == 2 {
        PyValueError::new_err(e.to_string())
    } else {
        PyRuntimeError::new_err(e.to_string())
    }
}

/// How often a long call looks for Python's pending signals (Ctrl-C).
const SIGNAL_POLL: std::time::Duration = std::time::Duration::from_millis(50);

/// Raised by the calling thread when Python has a pending signal (Ctrl-C), for long work
/// running elsewhere to stop at its next check; cheap to check from any thread.
#[derive(Clone, Default)]
struct Interrupt(std::sync::Arc<std::sync::atomic::AtomicBool>);

impl Interrupt {
    /// [`sisfilt::Error::Interrupted`] once a signal has come.
    fn check(&self) -> sisfilt::Result<()> {
        match self.0.load(std::sync::atomic::Ordering::Relaxed) {
            true => Err(sisfilt::Error::Interrupted),
            false => Ok(()),
        }
    }
}

/// Runs `work` on a thread of its own without the GIL (other Python threads run meanwhile),
/// handing it an [`Interrupt`]. Python runs signal handlers only on the thread that called
/// it, so that thread looks for them every [`SIGNAL_POLL`] while the work runs (on however
/// many threads it uses): a signal's exception (KeyboardInterrupt) is raised, any other
/// error as its kind ([`py_err`]).
fn without_gil<T: Send>(
    py: Python<'_>,
    work: impl FnOnce(Interrupt) -> sisfilt::Result<T> + Send,
) -> PyResult<T> {
    let interrupt = Interrupt::default();
    let mut signal: Option<PyErr> = None;
    let joined = py.detach(|| {
        std::thread::scope(|scope| {
            let caller = std::thread::current();
            let flag = interrupt.clone();
            let worker = scope.spawn(move || {
                let result = work(flag);
                caller.unpark();
                result
            });
            while !worker.is_finished() {
                std::thread::park_timeout(SIGNAL_POLL);
                if signal.is_none()
                    && !worker.is_finished()
                    && let Err(e) = Python::attach(|py| py.check_signals())
                {
                    signal = Some(e);
                    interrupt
                        .0
                        .store(true, std::sync::atomic::Ordering::Relaxed);
                }
            }
            worker.join()
        })
    });
    let result = joined.unwrap_or_else(|panic| std::panic::resume_unwind(panic));
    match signal {
        // The user asked to stop: so it is, even when the work finished first.
        Some(signal) => Err(signal),
        None => result.map_err(py_err),
    }
}

/// The value of the option `what` called `name`, or a `ValueError` listing the names.
fn choice<T: Choice>(what: &str, name: &str) -> PyResult<T> {
    T::from_name(name).ok_or_else(|| {
        let names: Vec<&str> = T::VARIANTS.iter().map(|v| v.name).collect();
        PyValueError::new_err(format!(
            "{what}: expected one of {}, found {name:?}",
            names.join(", ")
        ))
    })
}

/// The run settings given by name, as `estimate` and `Filter` take them (the rest default).
fn named_spec(
    filter: &str,
    update: &str,
    dropouts: &str,
    paper: bool,
    solver: Option<&str>,
    second_moment: Option<&str>,
    interconnect_from: Option<&str>,
) -> PyResult<RunSpec> {
    Ok(RunSpec {
        filter: choice("filter", filter)?,
        update: choice("update", update)?,
        dropouts: choice("dropouts", dropouts)?,
        paper,
        solver: solver.map(|s| choice("solver", s)).transpose()?,
        second_moment: second_moment
            .map(|s| choice("second_moment", s))
            .transpose()?,
        interconnect_from: interconnect_from
            .map(|s| choice("interconnect_from", s))
            .transpose()?,
        ..RunSpec::default()
    })
}

/// A serialisable value as the Python object its JSON reads as.
fn to_python<'py>(py: Python<'py>, value: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value)
        .map_err(|e| PyRuntimeError::new_err(format!("cannot convert to Python: {e}")))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// `values` as a float64 array of `shape`.
fn array<'py>(py: Python<'py>, values: Vec<f64>, shape: &[usize]) -> PyResult<Bound<'py, PyAny>> {
    let a = ArrayD::from_shape_vec(IxDyn(shape), values)
        .map_err(|e| PyRuntimeError::new_err(format!("array of shape {shape:?}: {e}")))?;
    Ok(a.into_pyarray(py).into_any())
}

/// The values of `a` in C order after checking its shape against `expected` (`None`: any
/// length on that axis), or a `ValueError` naming `what`.
fn values(
    a: &PyArrayLikeDyn<'_, f64, AllowTypeChange>,
    what: &str,
    expected: &[Option<usize>],
    names: &str,
) -> PyResult<Vec<f64>> {
    let shape = a.shape();
    let fits = shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(&s, e)| e.is_none_or(|e| e == s));
    if !fits {
        let want: Vec<String> = expected
            .iter()
            .map(|e| e.map_or("any".to_string(), |e| e.to_string()))
            .collect();
        return Err(PyValueError::new_err(format!(
            "{what}: expected an array of shape {names} = ({}), found {shape:?}",
            want.join(", ")
        )));
    }
    Ok(a.as_array().iter().copied().collect())
}

/// A chain model: the matrices, `N`, the dropout probabilities and the initial conditions,
/// checked as the command line checks a config.
#[pyclass(frozen, module = "sisfilt")]
struct Model {
    source: ConfigSource,
    inner: sisfilt::model::Model,
}

impl Model {
    fn from_source(source: ConfigSource) -> PyResult<Self> {
        let inner = sisfilt::model::Model::from_config(&source).map_err(py_err)?;
        Ok(Self { source, inner })
    }
}

#[pymethods]
impl Model {
    /// The model of the TOML config file at `path` (relative paths in it resolve against its
    /// folder).
    #[staticmethod]
    fn from_toml(py: Python<'_>, path: std::path::PathBuf) -> PyResult<Self> {
        let source = py
            .detach(|| ConfigSource::from_file(&path))
            .map_err(py_err)?;
        Self::from_source(source)
    }

    /// The model of config TOML held in a string; `name` names it in messages.
    #[staticmethod]
    #[pyo3(signature = (text, name = "<string>"))]
    fn from_toml_str(text: String, name: &str) -> PyResult<Self> {
        Self::from_source(ConfigSource::from_text(name, ".".into(), text).map_err(py_err)?)
    }

    /// A changed copy, as the command line's `--set` makes it: `p=0.7`, `M=[[0.02]]` (a
    /// matrix of `[model]` by its letter), `steps=500`, or any key by its dotted path
    /// (`**{"override[1].p": 0.3}`); values are numbers, booleans, strings, lists or arrays.
    #[pyo3(signature = (**changes))]
    fn with_(&self, py: Python<'_>, changes: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
        let mut settings = Vec::new();
        let json = py.import("json")?;
        for (key, value) in changes
            .map(|d| d.iter().collect::<Vec<_>>())
            .unwrap_or_default()
        {
            let key: String = key.extract()?;
            let path = match key.as_str() {
                "p" => "dropout.p".to_string(),
                k if sisfilt::model::MATRIX_KEYS.contains(&k) => format!("model.{k}"),
                k => k.to_string(),
            };
            let value = if value.hasattr("tolist")? {
                value.call_method0("tolist")?
            } else {
                value
            };
            let text: String = json.call_method1("dumps", (value,))?.extract()?;
            settings.push(ConfigSetting {
                key: path,
                value: text,
            });
        }
        Self::from_source(
            self.source
                .clone()
                .with_settings(&settings)
                .map_err(py_err)?,
        )
    }

    /// The figures of `sisfilt check` as a dict.
    fn check<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let model = self.inner.clone();
        let report = py
            .detach(|| sisfilt::check::check(&model))
            .map_err(py_err)?;
        to_python(py, &report)
    }

    /// Chain length `N`.
    #[getter]
    fn subsystems(&self) -> usize {
        self.inner.subsystems
    }

    /// State dimension `n` of each subsystem.
    #[getter]
    fn n(&self) -> usize {
        self.inner.dims.n
    }

    /// Measurement dimension `q`.
    #[getter]
    fn q(&self) -> usize {
        self.inner.dims.q
    }

    /// Input dimension `m`.
    #[getter]
    fn m(&self) -> usize {
        self.inner.dims.m
    }

    /// The config's `steps`, or `None`.
    #[getter]
    fn steps(&self) -> Option<usize> {
        self.inner.steps
    }

    /// The config as TOML (with every change of `with_` applied).
    fn to_toml(&self) -> PyResult<String> {
        Ok(ConfigSource::from_raw(
            &self.source.name,
            self.source.dir.clone(),
            self.source.raw.clone(),
        )
        .map_err(py_err)?
        .text)
    }

    fn __repr__(&self) -> String {
        format!(
            "Model({}: N = {}, n = {}, q = {}, m = {})",
            self.source.name,
            self.inner.subsystems,
            self.inner.dims.n,
            self.inner.dims.q,
            self.inner.dims.m
        )
    }
}

/// Simulates the chain for `steps` steps (default: the config's) with `seed` (default: the
/// config's): a dict of `x[T,N,n]`, `y[T,N,q]` (a lost measurement holds its noise, as the
/// paper's model says; NaN where a subsystem has no sensor), `gamma[T,N]` (True where the
/// measurement arrived) and `u[T,N,m]`. Arrays above `max_memory` bytes in all are refused
/// before anything is allocated.
#[pyfunction]
#[pyo3(signature = (model, seed = None, steps = None, *, max_memory = DEFAULT_MAX_MEMORY))]
fn simulate<'py>(
    py: Python<'py>,
    model: &Model,
    seed: Option<u64>,
    steps: Option<usize>,
    max_memory: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let m = model.inner.clone();
    let steps = match steps {
        Some(0) => return Err(PyValueError::new_err("steps: expected at least 1")),
        Some(s) => s,
        None => m.horizon().map_err(py_err)?,
    };
    let (big_n, d) = (m.subsystems, m.dims);
    // x, y and u in float64, gamma in bool.
    let need = steps as f64 * big_n as f64 * ((d.n + d.q + d.m) * 8 + 1) as f64;
    if need > max_memory as f64 {
        return Err(PyValueError::new_err(format!(
            "steps = {steps}: the arrays of {steps} steps of {big_n} subsystems take {} ({need:.3e} bytes), above max_memory = {} ({max_memory} bytes); simulate fewer steps, or raise max_memory",
            human_bytes(need as u64),
            human_bytes(max_memory)
        )));
    }
    // The room up front: what does not fit is a MemoryError, not an abort, and the arrays are
    // not copied as they grow.
    fn room<T>(values: Option<usize>) -> PyResult<Vec<T>> {
        let mut v = Vec::new();
        values
            .ok_or_else(|| "capacity overflow".to_string())
            .and_then(|len| v.try_reserve_exact(len).map_err(|e| e.to_string()))
            .map_err(|e| PyMemoryError::new_err(format!("simulate: {e}")))?;
        Ok(v)
    }
    let cells = steps.checked_mul(big_n);
    let of = |width: usize| cells.and_then(|c| c.checked_mul(width));
    let (mut x, mut y, mut gamma, mut u) =
        (room(of(d.n))?, room(of(d.q))?, room(cells)?, room(of(d.m))?);
    let seed = seed.unwrap_or(m.seed);
    let (x, y, gamma, u) = without_gil(py, |interrupt| {
        let mut inputs = sisfilt::inputs::InputStream::open(&m, None)?;
        let mut y_t = vec![0.0; m.subsystems * m.dims.q];
        sisfilt::simulate::simulate(&m, steps, seed, &mut inputs, |s| {
            interrupt.check()?;
            x.extend_from_slice(s.x);
            y_t.copy_from_slice(s.y);
            m.blank_unmeasured(s.t, &mut y_t);
            y.extend_from_slice(&y_t);
            gamma.extend_from_slice(s.gamma);
            u.extend_from_slice(s.u);
            Ok(())
        })?;
        Ok((x, y, gamma, u))
    })?;
    let out = PyDict::new(py);
    out.set_item("x", array(py, x, &[steps, big_n, d.n])?)?;
    out.set_item("y", array(py, y, &[steps, big_n, d.q])?)?;
    let gamma = ArrayD::from_shape_vec(IxDyn(&[steps, big_n]), gamma)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    out.set_item("gamma", gamma.into_pyarray(py))?;
    out.set_item("u", array(py, u, &[steps, big_n, d.m])?)?;
    Ok(out)
}

/// The inputs `u[T,N,m]` as values, checked against `y`'s `T`; `None` gives the model's own.
fn inputs(
    model: &sisfilt::model::Model,
    u: Option<PyArrayLikeDyn<'_, f64, AllowTypeChange>>,
    steps: usize,
) -> PyResult<Option<Vec<f64>>> {
    u.map(|u| {
        values(
            &u,
            "u",
            &[Some(steps), Some(model.subsystems), Some(model.dims.m)],
            "(T, N, m)",
        )
    })
    .transpose()
}

/// The measurements `y[T,N,q]` as values (NaN: not in the data) and `T`.
fn measurements(
    model: &sisfilt::model::Model,
    y: &PyArrayLikeDyn<'_, f64, AllowTypeChange>,
) -> PyResult<(Vec<f64>, usize)> {
    let values = values(
        y,
        "y",
        &[None, Some(model.subsystems), Some(model.dims.q)],
        "(T, N, q)",
    )?;
    let steps = y.shape()[0];
    if steps == 0 {
        return Err(PyValueError::new_err("y: holds no step (T = 0)"));
    }
    Ok((values, steps))
}

/// The estimates of a run: `x[T,N,n]`, the diagonal blocks `P[T,N,n,n]` of the error
/// covariance, `arrival[T,N]` (`π`, with the mixture update) or None, `nis[T,N]` (NaN where
/// nothing was received), `loglik` (None without a density), the innovation check as a dict,
/// and the notes the command line prints as warnings.
#[pyclass(frozen, module = "sisfilt")]
struct Estimates {
    #[pyo3(get)]
    x: Py<PyAny>,
    #[pyo3(get, name = "P")]
    p: Py<PyAny>,
    #[pyo3(get)]
    arrival: Option<Py<PyAny>>,
    #[pyo3(get)]
    nis: Py<PyAny>,
    #[pyo3(get)]
    loglik: Option<f64>,
    /// The innovation check (docs/theory.md §14), converted to a dict when first read: with
    /// a figure per subsystem it is the largest thing to convert, and few calls read it.
    innovations: Option<sisfilt::innovations::InnovationReport>,
    /// With `hold_out`: the scores on the readings kept from the filter (docs/theory.md §17).
    held_out: Option<sisfilt::accuracy::HeldOutReport>,
    #[pyo3(get)]
    notes: Vec<String>,
    /// What the rows hold: `filtered`, `predicted` or `smoothed`.
    #[pyo3(get)]
    kind: String,
    /// Seconds the library spent taking the steps from the arrays (`read`), filtering
    /// (`filter`), scoring the innovations (`check`) and collecting the estimates (`write`),
    /// and its whole run (`run`: those and the run's setup and checks).
    #[pyo3(get)]
    timings: Py<PyAny>,
}

#[pymethods]
impl Estimates {
    /// The innovation check as a dict (the JSON's `innovations`): whether the data fit the
    /// model, with a figure per subsystem.
    #[getter]
    fn innovations<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.innovations)
    }

    /// With `hold_out`, the scores on the readings kept from the filter as a dict (the
    /// JSON's `held_out`: `readings`, `rmse`, `interpolation_rmse`, `standardised`, …);
    /// else None.
    #[getter]
    fn held_out<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.held_out)
    }

    /// The columns of the estimates CSV (`t,i,x1..xn,P1_1,P1_2..Pn_n`, then `arrival` and
    /// `nis`; `t_given` for `t` with predicted estimates) as a pandas DataFrame, one row per
    /// `(t, i)`. Needs pandas.
    fn to_pandas<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let pandas = py.import("pandas").map_err(|_| {
            PyErr::new::<pyo3::exceptions::PyImportError, _>(
                "to_pandas needs pandas: pip install pandas",
            )
        })?;
        let x = self.x.bind(py);
        let shape: Vec<usize> = x.getattr("shape")?.extract()?;
        let (steps, big_n, n) = (shape[0], shape[1], shape[2]);
        let np = py.import("numpy")?;
        let columns = PyDict::new(py);
        let rows = steps * big_n;
        let t: Vec<i64> = (0..rows).map(|r| (r / big_n + 1) as i64).collect();
        let i: Vec<i64> = (0..rows).map(|r| (r % big_n + 1) as i64).collect();
        let step_name = if self.kind == "predicted" {
            "t_given"
        } else {
            "t"
        };
        columns.set_item(step_name, np.call_method1("asarray", (t,))?)?;
        columns.set_item("i", np.call_method1("asarray", (i,))?)?;
        let x_rows = x.call_method1("reshape", (rows, n))?;
        for k in 0..n {
            columns.set_item(
                format!("x{}", k + 1),
                x_rows.get_item((PySlice::full(py), k))?,
            )?;
        }
        let p_rows = self.p.bind(py).call_method1("reshape", (rows, n, n))?;
        for r in 0..n {
            for c in r..n {
                columns.set_item(
                    format!("P{}_{}", r + 1, c + 1),
                    p_rows.get_item((PySlice::full(py), r, c))?,
                )?;
            }
        }
        if let Some(arrival) = &self.arrival {
            columns.set_item(
                "arrival",
                arrival.bind(py).call_method1("reshape", (rows,))?,
            )?;
        }
        columns.set_item("nis", self.nis.bind(py).call_method1("reshape", (rows,))?)?;
        pandas.call_method1("DataFrame", (columns,))
    }

    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let shape: Vec<usize> = self.x.bind(py).getattr("shape")?.extract()?;
        Ok(format!(
            "Estimates({}, x of shape {shape:?}, loglik {:?})",
            self.kind, self.loglik
        ))
    }
}

/// Runs a filter (or smoother) over measurements `y[T,N,q]` (NaN marks a value not in the
/// data, as an empty cell does in a file) with inputs `u[T,N,m]` (default: the model's own):
/// every option of `sisfilt estimate`, by the same names in snake case.
#[pyfunction]
#[pyo3(signature = (
    model, y, u = None, *, filter = "distributed", update = "linear", dropouts = "unknown",
    smooth = false, predicted = false, paper = false, solver = None, second_moment = None,
    interconnect_from = None, band = None, band_tol = None, loading = None,
    max_lifted = DEFAULT_MAX_LIFTED, max_memory = None, hold_out = None, seed = 1
))]
#[allow(clippy::too_many_arguments)]
fn estimate(
    py: Python<'_>,
    model: &Model,
    y: PyArrayLikeDyn<'_, f64, AllowTypeChange>,
    u: Option<PyArrayLikeDyn<'_, f64, AllowTypeChange>>,
    filter: &str,
    update: &str,
    dropouts: &str,
    smooth: bool,
    predicted: bool,
    paper: bool,
    solver: Option<&str>,
    second_moment: Option<&str>,
    interconnect_from: Option<&str>,
    band: Option<usize>,
    band_tol: Option<f64>,
    loading: Option<f64>,
    max_lifted: usize,
    max_memory: Option<u64>,
    hold_out: Option<f64>,
    seed: u64,
) -> PyResult<Estimates> {
    let spec = RunSpec {
        hold_out,
        hold_out_seed: seed,
        band,
        band_tol,
        loading,
        smooth,
        predicted,
        max_lifted,
        max_memory,
        nis_column: true,
        ..named_spec(
            filter,
            update,
            dropouts,
            paper,
            solver,
            second_moment,
            interconnect_from,
        )?
    }
    .check()
    .map_err(|e| py_err(e.into()))?;
    let m = model.inner.clone();
    let (y, steps) = measurements(&m, &y)?;
    let u = inputs(&m, u, steps)?;
    let started = std::time::Instant::now();
    let run = without_gil(py, |interrupt| {
        sisfilt::run::estimate_interruptible(&m, &spec, &y, u.as_deref(), None, &mut || {
            interrupt.check()
        })
    })?;
    let run_seconds = started.elapsed().as_secs_f64();
    let (big_n, n) = (m.subsystems, m.dims.n);
    Ok(Estimates {
        x: array(py, run.x, &[steps, big_n, n])?.unbind(),
        p: array(py, run.p, &[steps, big_n, n, n])?.unbind(),
        arrival: run
            .arrival
            .map(|a| array(py, a, &[steps, big_n]).map(Bound::unbind))
            .transpose()?,
        nis: array(py, run.nis, &[steps, big_n])?.unbind(),
        loglik: run.report.summary.loglik,
        innovations: run.report.summary.innovations,
        held_out: run.report.summary.held_out,
        notes: run.notes.iter().map(ToString::to_string).collect(),
        kind: to_python(py, &spec.output())?.extract()?,
        timings: {
            let t = run.report.timings;
            let d = PyDict::new(py);
            d.set_item("read", t.read.as_secs_f64())?;
            d.set_item("filter", t.filter.as_secs_f64())?;
            d.set_item("check", t.check.as_secs_f64())?;
            d.set_item("write", t.write.as_secs_f64())?;
            d.set_item("run", run_seconds)?;
            d.into_any().unbind()
        },
    })
}

/// Fits `p` and the diagonals of `Q` and `M` to `y[T,N,q]` by maximum likelihood (docs/theory.md
/// §16): returns the report (the JSON of `sisfilt fit` as a dict) and the fitted model.
#[pyfunction]
#[pyo3(signature = (
    model, y, u = None, *, params = None, filter = "joint", band = None, dropouts = "unknown",
    max_iter = sisfilt::fit::DEFAULT_MAX_ITER, max_memory = None
))]
#[allow(clippy::too_many_arguments)]
fn fit<'py>(
    py: Python<'py>,
    model: &Model,
    y: PyArrayLikeDyn<'_, f64, AllowTypeChange>,
    u: Option<PyArrayLikeDyn<'_, f64, AllowTypeChange>>,
    params: Option<Vec<String>>,
    filter: &str,
    band: Option<usize>,
    dropouts: &str,
    max_iter: usize,
    max_memory: Option<u64>,
) -> PyResult<(Bound<'py, PyAny>, Model)> {
    let dropouts: sisfilt::filter::Dropouts = choice("dropouts", dropouts)?;
    let params = match params {
        Some(names) => names
            .iter()
            .map(|n| n.parse::<ParamGroup>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| py_err(e.into()))?,
        None if dropouts == sisfilt::filter::Dropouts::Known => vec![ParamGroup::Q, ParamGroup::M],
        None => vec![ParamGroup::P, ParamGroup::Q, ParamGroup::M],
    };
    let spec = FitSpec {
        params,
        filter: choice("filter", filter)?,
        band,
        dropouts,
        max_iter,
        max_memory,
    }
    .check()
    .map_err(py_err)?;
    let m = model.inner.clone();
    let (y, steps) = measurements(&m, &y)?;
    let u = inputs(&m, u, steps)?;
    let fitted = without_gil(py, |interrupt| {
        let progress: sisfilt::fit::ProgressFn = Box::new(move |_| interrupt.check());
        sisfilt::fit::fit(&m, &spec, &y, u.as_deref(), Some(progress))
    })?;
    let raw = fitted.fitted_config(&model.source.raw);
    let source = ConfigSource::from_raw(&model.source.name, model.source.dir.clone(), raw)
        .map_err(py_err)?;
    Ok((to_python(py, &fitted.report)?, Model::from_source(source)?))
}

/// The Monte Carlo comparison of `sisfilt evaluate`: `runs` runs (seeds `seed..seed+runs−1`,
/// default the config's) of every filter (or those named in `filters`) on the same simulated
/// realisations; with `sweep_p`, once per assumed arrival probability. Returns the JSON of
/// `evaluate --out` as a dict; with `shard = (K, M)` only shard `K` of `M` of the study, as
/// `evaluate --shard K/M --out` writes it, for [`evaluate_merge`].
#[pyfunction]
#[pyo3(signature = (
    model, runs, *, seed = None, burn_in = 0, max_lifted = DEFAULT_MAX_LIFTED,
    band = sisfilt::filter::joint::DEFAULT_BAND, loading = None, filters = None, smooth = false,
    sweep_p = None, true_p = None, shard = None, max_memory = DEFAULT_MAX_MEMORY
))]
#[allow(clippy::too_many_arguments)]
fn evaluate<'py>(
    py: Python<'py>,
    model: &Model,
    runs: usize,
    seed: Option<u64>,
    burn_in: usize,
    max_lifted: usize,
    band: usize,
    loading: Option<f64>,
    filters: Option<Vec<String>>,
    smooth: bool,
    sweep_p: Option<Vec<f64>>,
    true_p: Option<f64>,
    shard: Option<(usize, usize)>,
    max_memory: u64,
) -> PyResult<Bound<'py, PyAny>> {
    let shard = shard
        .map(|(index, count)| sisfilt::evaluate::Shard::new(index, count))
        .transpose()
        .map_err(|e| py_err(e.into()))?;
    let filters = filters
        .unwrap_or_default()
        .iter()
        .map(|name| choice("filters", name))
        .collect::<PyResult<Vec<_>>>()?;
    let m = model.inner.clone();
    let opts = sisfilt::evaluate::EvaluateOptions {
        runs,
        seed: seed.unwrap_or(m.seed),
        burn_in,
        max_lifted,
        band,
        loading,
        filters,
        smooth,
        true_p,
        max_memory,
    };
    // As the command line names it: the config, then its settings.
    let name = std::iter::once(model.source.name.clone())
        .chain(model.source.settings.iter().map(|s| format!("--set {s}")))
        .collect::<Vec<_>>()
        .join(" ");
    let value = without_gil(py, |interrupt| -> sisfilt::Result<serde_json::Value> {
        let tick = || interrupt.check();
        let inputs = sisfilt::inputs::RunInputs::of_model(&m)?;
        let sweep = sweep_p.as_deref();
        Ok(match (shard, sweep) {
            (Some(shard), _) => serde_json::to_value(sisfilt::evaluate::evaluate_part(
                &m, &inputs, &name, opts, sweep, shard, tick,
            )?),
            (None, Some(values)) => serde_json::to_value(sisfilt::evaluate::sweep_p(
                &m, &inputs, &name, opts, values, tick,
            )?),
            (None, None) => {
                serde_json::to_value(sisfilt::evaluate::evaluate(&m, &inputs, &name, opts, tick)?)
            }
        }
        .expect("an evaluation serialises"))
    })?;
    to_python(py, &value)
}

/// The parts of a sharded study (`evaluate(…, shard=(K, M))`, or the JSON files of `evaluate
/// --shard K/M --out`, read with `json.load`), every shard once and in any order, added up
/// into the dict `evaluate` returns for the whole study. Parts of different studies, a shard
/// given twice or one missing raise `ValueError` naming them by their place in `parts`.
#[pyfunction]
fn evaluate_merge<'py>(
    py: Python<'py>,
    parts: Vec<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    let dumps = py.import("json")?.getattr("dumps")?;
    let parts = parts
        .iter()
        .enumerate()
        .map(|(k, part)| {
            let name = format!("parts[{k}]");
            let text: String = dumps.call1((part,))?.extract()?;
            let part = serde_json::from_str(&text).map_err(|e| {
                PyValueError::new_err(format!(
                    "{name}: not a part of a study (evaluate(…, shard=(K, M))): {e}"
                ))
            })?;
            Ok((name, part))
        })
        .collect::<PyResult<Vec<_>>>()?;
    let study = sisfilt::evaluate::merge(&parts).map_err(|e| py_err(e.into()))?;
    to_python(py, &study)
}

/// The Python module `sisfilt._sisfilt`, re-exported by `sisfilt`.
#[pymodule]
fn _sisfilt(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<Model>()?;
    module.add_class::<Estimates>()?;
    module.add_class::<Filter>()?;
    module.add_function(wrap_pyfunction!(simulate, module)?)?;
    module.add_function(wrap_pyfunction!(estimate, module)?)?;
    module.add_function(wrap_pyfunction!(fit, module)?)?;
    module.add_function(wrap_pyfunction!(evaluate, module)?)?;
    module.add_function(wrap_pyfunction!(evaluate_merge, module)?)?;
    module.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
