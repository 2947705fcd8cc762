//! The step-by-step filter of the Python package (`sisfilt.Filter`): the library's filters
//! one time step at a time, for data that arrive as they are measured.

use numpy::{AllowTypeChange, PyArrayLikeDyn};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use sisfilt::filter::centralized::DEFAULT_MAX_LIFTED;
use sisfilt::run::RunSpec;

use crate::{Model, array, named_spec, py_err, values};

/// A filter run step by step, for data that arrive as they are measured:
/// `f = Filter(model, filter="joint", update="mixture")`, then `x, P = f.step(y_t, u_t)` with
/// `y_t[N,q]` (NaN: not in the data) and `u_t[N,m]` (default: the model's own inputs at that
/// step). The estimates equal those of `estimate` on the same steps.
#[pyclass(module = "sisfilt")]
pub(crate) struct Filter {
    model: sisfilt::model::Model,
    state: std::sync::Mutex<FilterState>,
}

/// What a step-by-step filter keeps between steps.
struct FilterState {
    filter: Box<dyn sisfilt::filter::ChainFilter>,
    inputs: sisfilt::inputs::InputStream,
    /// The last step run (0 before the first).
    t: usize,
    y: Vec<f64>,
    u: Vec<f64>,
}

impl Filter {
    fn state(&self) -> PyResult<std::sync::MutexGuard<'_, FilterState>> {
        self.state
            .lock()
            .map_err(|_| PyRuntimeError::new_err("the filter broke down in another thread"))
    }

    /// `(x[N,n], P[N,n,n])` of the estimates `(x, p)`.
    fn pair<'py>(
        &self,
        py: Python<'py>,
        x: &[f64],
        p: &[f64],
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let (big_n, n) = (self.model.subsystems, self.model.dims.n);
        Ok((
            array(py, x.to_vec(), &[big_n, n])?,
            array(py, p.to_vec(), &[big_n, n, n])?,
        ))
    }
}

#[pymethods]
impl Filter {
    #[new]
    #[pyo3(signature = (
        model, *, filter = "distributed", update = "linear", dropouts = "unknown", paper = false,
        solver = None, second_moment = None, interconnect_from = None, band = None,
        band_tol = None, loading = None, max_lifted = DEFAULT_MAX_LIFTED, max_memory = None
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        model: &Model,
        filter: &str,
        update: &str,
        dropouts: &str,
        paper: bool,
        solver: Option<&str>,
        second_moment: Option<&str>,
        interconnect_from: Option<&str>,
        band: Option<usize>,
        band_tol: Option<f64>,
        loading: Option<f64>,
        max_lifted: usize,
        max_memory: Option<u64>,
    ) -> PyResult<Self> {
        let spec = RunSpec {
            band,
            band_tol,
            loading,
            max_lifted,
            max_memory,
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
        let filter = spec.build_filter(&m).map_err(py_err)?;
        let inputs = sisfilt::inputs::InputStream::open(&m, None).map_err(py_err)?;
        let state = FilterState {
            filter,
            inputs,
            t: 0,
            y: vec![0.0; m.subsystems * m.dims.q],
            u: vec![0.0; m.subsystems * m.dims.m],
        };
        Ok(Self {
            model: m,
            state: std::sync::Mutex::new(state),
        })
    }

    /// Runs the next step on `y_t[N,q]` and `u_t[N,m]`; returns `x̂(t|t)[N,n]` and the
    /// diagonal blocks of `P(t|t)[N,n,n]`.
    #[pyo3(signature = (y_t, u_t = None))]
    fn step<'py>(
        &self,
        py: Python<'py>,
        y_t: PyArrayLikeDyn<'_, f64, AllowTypeChange>,
        u_t: Option<PyArrayLikeDyn<'_, f64, AllowTypeChange>>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let (big_n, d) = (self.model.subsystems, self.model.dims);
        let y = values(&y_t, "y_t", &[Some(big_n), Some(d.q)], "(N, q)")?;
        if let Some(k) = y.iter().position(|v| v.is_infinite()) {
            return Err(PyValueError::new_err(format!(
                "y_t: i = {}, element {}: expected a finite number or NaN (not in the data), found {}",
                k / d.q + 1,
                k % d.q + 1,
                y[k]
            )));
        }
        let u = u_t
            .map(|u| values(&u, "u_t", &[Some(big_n), Some(d.m)], "(N, m)"))
            .transpose()?;
        let mut state = self.state()?;
        let st = &mut *state;
        let t = st.t + 1;
        st.y.copy_from_slice(&y);
        self.model.blank_unmeasured(t, &mut st.y);
        match u {
            Some(u) => st.u.copy_from_slice(&u),
            None => st.inputs.next(t, &mut st.u).map_err(py_err)?,
        }
        let (filter, y, u) = (&mut st.filter, &st.y, &st.u);
        py.detach(|| filter.step(y, u)).map_err(py_err)?;
        st.t = t;
        let (x, p) = st.filter.filtered();
        sisfilt::filter::check_estimates(t, d.n, x, p).map_err(py_err)?;
        self.pair(py, x, p)
    }

    /// `x̂(t+1|t)[N,n]` and the diagonal blocks of `T(t+1)[N,n,n]` after the last step.
    fn predicted<'py>(&self, py: Python<'py>) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let state = self.state()?;
        let (x, p) = state.filter.predicted();
        self.pair(py, x, p)
    }

    /// `π(t, ·)[N]` of the last step (the mixture update), else None.
    #[getter]
    fn arrival<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let state = self.state()?;
        state
            .filter
            .arrival()
            .map(|a| array(py, a.to_vec(), &[a.len()]))
            .transpose()
    }

    /// The log density of the last step's measurements given the past, when the filter has one.
    #[getter]
    fn loglik(&self) -> PyResult<Option<f64>> {
        Ok(self.state()?.filter.log_likelihood())
    }

    /// The last step run (0 before the first).
    #[getter]
    fn t(&self) -> PyResult<usize> {
        Ok(self.state()?.t)
    }
}
