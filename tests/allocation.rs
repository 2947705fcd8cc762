//! The hot loops allocate nothing: a counting global allocator records every allocation while
//! the filter runs its steps after the first ones (step 1 may size buffers, and a change of
//! parameters between override windows may refactorise step 1's system), for each variant of
//! the distributed filter, sequential and in parallel, and of the joint band-k filter, and
//! while the CSV reader and the estimates writer stream their steps; and the memory bounds the
//! filters are checked against before they are built hold what they allocate.
//!
//! One test function only: the counter is global, and test functions run in parallel.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use sisfilt::config::ConfigSource;
use sisfilt::filter::kernel::DynamicKernel;
use sisfilt::filter::{
    ChainFilter, Dropouts, JointFilter, JointOptions, SecondMoment, TwoStepFilter, TwoStepOptions,
    Update,
};
use sisfilt::innovations::InnovationCheck;
use sisfilt::interconnect::SolverKind;
use sisfilt::io::estimates::{
    BackgroundWriter, EstimatesColumns, EstimatesWriter, Format, RowValues,
};
use sisfilt::io::{StepLayout, StepReader};
use sisfilt::model::Model;

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);
/// Bytes allocated and not yet freed, and the most of them since [`peak_bytes_in`] reset it.
static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grow(bytes: usize) {
    let live = LIVE.fetch_add(bytes, Ordering::Relaxed) + bytes;
    PEAK.fetch_max(live, Ordering::Relaxed);
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        grow(layout.size());
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        grow(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// The most bytes held at once while `f` runs, beyond those held when it starts.
fn peak_bytes_in(f: impl FnOnce()) -> usize {
    let before = LIVE.load(Ordering::SeqCst);
    PEAK.store(before, Ordering::SeqCst);
    f();
    PEAK.load(Ordering::SeqCst) - before
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A pool whose threads have all started (a starting thread allocates, and the counter is
/// global).
fn started_pool(threads: usize) -> rayon::ThreadPool {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.broadcast(|_| ());
    pool
}

/// Allocations while `f` runs, the least over three runs: the counter is global, and a thread
/// of the pool may now and then allocate for its own bookkeeping (rayon's sleep and wake-up)
/// while `f` runs, but an allocation in the loop itself happens in every run.
fn allocations_in(mut f: impl FnMut()) -> usize {
    (0..3)
        .map(|_| {
            let before = ALLOCATIONS.load(Ordering::SeqCst);
            f();
            ALLOCATIONS.load(Ordering::SeqCst) - before
        })
        .min()
        .unwrap()
}

fn model(subsystems: usize, p: &str, extra: &str) -> Model {
    model_of(subsystems, 13, p, extra)
}

fn model_of(subsystems: usize, steps: usize, p: &str, extra: &str) -> Model {
    let text = format!(
        "subsystems = {subsystems}\nsteps = {steps}\n[interconnection]\nplus = 1\nminus = 1\n\
         [model]\nA = [[0.9, 0.1], [-0.1, 0.8]]\nB = [[0.1, 0.05], [0.05, 0.1]]\n\
         C = [[0.0], [0.1]]\nD = [[0.3, 0.1], [0.1, 0.3]]\nG = [[0.1, 0.2], [0.2, 0.1]]\n\
         J = [[1.0, 0.0]]\nR = [[0.1]]\nM = [[0.1]]\nQ = [[0.01, 0.0], [0.0, 0.01]]\n\
         [dropout]\np = {p}\n[initial]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n\
         [input]\nkind = \"sine\"\nperiod = 5.0\nphase = 0.1\n{extra}"
    );
    Model::from_config(&ConfigSource::from_text("alloc.toml", ".".into(), text).unwrap()).unwrap()
}

/// Runs 13 steps; returns the allocations of steps 5..13 (three runs of three steps), after
/// every window change of the models below. With `known`, every third measurement is lost (an empty cell, NaN).
fn steps_allocate(filter: &mut dyn ChainFilter, model: &Model, known: bool) -> usize {
    let (big_n, q, m) = (model.subsystems, model.dims.q, model.dims.m);
    let mut y: Vec<f64> = (0..big_n * q).map(|k| (k as f64 * 0.3).sin()).collect();
    if known {
        y.iter_mut().step_by(3).for_each(|v| *v = f64::NAN);
    }
    let u: Vec<f64> = (0..big_n * m).map(|k| (k as f64 * 0.7).cos()).collect();
    for _ in 1..=4 {
        filter.step(&y, &u).unwrap();
    }
    allocations_in(|| {
        for _ in 5..=7 {
            filter.step(&y, &u).unwrap();
        }
    })
}

#[test]
fn steps_after_the_first_allocate_nothing() {
    let pool = started_pool(2);
    let homogeneous = model(50, "0.8", "");
    let varying = model(
        50,
        "0.8",
        "[[override]]\nsubsystems = [3, 9]\nA = [[0.8, 0.0], [0.0, 0.7]]\nG = [[0.2, 0.1], [0.1, 0.2]]\n\
         [[override]]\nsteps = [2, 3]\nG = [[0.2, 0.0], [0.0, 0.2]]\n",
    );
    // Long enough for the parallel path (4096 subsystems and more).
    let long = model(5000, "0.8", "");
    let long_varying = model(
        5000,
        "0.8",
        "[[override]]\nsubsystems = [1, 2500]\nA = [[0.8, 0.0], [0.0, 0.7]]\n",
    );
    let mut cases: Vec<(String, &Model, TwoStepOptions)> = Vec::new();
    for (name, model) in [
        ("homogeneous", &homogeneous),
        ("varying", &varying),
        ("long", &long),
        ("long varying", &long_varying),
    ] {
        // The lifted moment is dense, `(N n)²` numbers: not on the long chains.
        let moments: &[SecondMoment] = if model.subsystems > 100 {
            &[SecondMoment::Local, SecondMoment::Paper]
        } else {
            &[
                SecondMoment::Local,
                SecondMoment::Paper,
                SecondMoment::Lifted,
            ]
        };
        for &second_moment in moments {
            for dropouts in [Dropouts::Unknown, Dropouts::Known] {
                // The transfer recursion overflows on long chains (docs/theory.md §2).
                let solvers: &[SolverKind] = if model.subsystems > 100 {
                    &[SolverKind::Banded]
                } else {
                    &[SolverKind::Banded, SolverKind::Transfer]
                };
                for &solver in solvers {
                    let opts = TwoStepOptions {
                        second_moment,
                        dropouts,
                        solver,
                        ..TwoStepOptions::default()
                    };
                    cases.push((format!("{name} {opts:?}"), model, opts));
                }
            }
        }
        // The mixture update (docs/theory.md §10), unknown dropouts only.
        let opts = TwoStepOptions {
            update: Update::Mixture,
            ..TwoStepOptions::default()
        };
        cases.push((format!("{name} {opts:?}"), model, opts));
    }
    for (name, model, opts) in &cases {
        let known = opts.dropouts == Dropouts::Known;
        pool.install(|| {
            let mut fixed = sisfilt::filter::two_step(model, *opts).unwrap();
            let count = steps_allocate(fixed.as_mut(), model, known);
            assert_eq!(count, 0, "{name}, compile-time sizes: {count} allocations");
            let mut dynamic = TwoStepFilter::<DynamicKernel>::new(model, *opts).unwrap();
            let count = steps_allocate(&mut dynamic, model, known);
            assert_eq!(count, 0, "{name}, dynamic sizes: {count} allocations");
            let mut unshared = TwoStepFilter::<DynamicKernel>::new(model, *opts)
                .unwrap()
                .without_sharing();
            let count = steps_allocate(&mut unshared, model, known);
            assert_eq!(count, 0, "{name}, without sharing: {count} allocations");
        });
    }

    // The joint band-k filter (docs/theory.md §8) with each second moment, both dropout modes
    // and the mixture update, at a narrow and a wide band.
    for (name, model) in [("homogeneous", &homogeneous), ("varying", &varying)] {
        for band in [1, 4] {
            let mut options = vec![
                JointOptions {
                    dropouts: Dropouts::Known,
                    ..JointOptions::default()
                },
                JointOptions {
                    update: Update::Mixture,
                    ..JointOptions::default()
                },
            ];
            for second_moment in [
                SecondMoment::Band,
                SecondMoment::Lifted,
                SecondMoment::Local,
            ] {
                options.push(JointOptions {
                    second_moment,
                    ..JointOptions::default()
                });
            }
            for opts in options {
                let opts = JointOptions { band, ..opts };
                let known = opts.dropouts == Dropouts::Known;
                pool.install(|| {
                    let mut joint = JointFilter::new(model, opts).unwrap();
                    let count = steps_allocate(&mut joint, model, known);
                    assert_eq!(count, 0, "{name}, joint {opts:?}: {count} allocations");
                });
            }
        }
    }

    // One subsystem's mixture pseudo-measurement (docs/theory.md §10), as the joint and the
    // centralized mixture filters call it for every subsystem of every step.
    {
        use nalgebra::DMatrix;
        use sisfilt::filter::nahi::{Measurement, Workspace, mixture_pseudo_measurement};
        let j = DMatrix::from_row_slice(2, 3, &[1.0, 0.5, 0.0, 0.0, -0.3, 2.0]);
        let m = DMatrix::from_row_slice(2, 2, &[0.4, 0.1, 0.1, 0.3]);
        let sigma = [1.2, 0.3, -0.1, 0.3, 0.8, 0.2, -0.1, 0.2, 0.5];
        let meas = Measurement {
            j: &j,
            m: &m,
            y: &[0.15, 1.2],
            ru: &[0.2, -0.1],
            p: 0.5,
            known: false,
        };
        let mut ws = Workspace::new(3, 2);
        let (mut w, mut r) = ([0.0; 4], [0.0; 2]);
        let x = [0.4, -1.0, 2.0];
        mixture_pseudo_measurement(&meas, &x, &sigma, &mut w, &mut r, &mut ws).unwrap();
        let count = allocations_in(|| {
            for _ in 0..3 {
                mixture_pseudo_measurement(&meas, &x, &sigma, &mut w, &mut r, &mut ws).unwrap();
            }
        });
        assert_eq!(count, 0, "mixture pseudo-measurement: {count} allocations");
    }

    // The innovation check (docs/theory.md §14) of each update and dropout mode, as every run
    // makes it before each step, over a block boundary (t = 25).
    for (dropouts, update) in [
        (Dropouts::Unknown, Update::Linear),
        (Dropouts::Unknown, Update::Mixture),
        (Dropouts::Known, Update::Linear),
    ] {
        let model = &varying;
        let (big_n, n) = (model.subsystems, model.dims.n);
        let mut check = InnovationCheck::new(model, dropouts, update, false);
        let mut y: Vec<f64> = (0..big_n).map(|k| (k as f64 * 0.3).sin()).collect();
        if dropouts == Dropouts::Known {
            y.iter_mut().step_by(3).for_each(|v| *v = f64::NAN);
        }
        let u: Vec<f64> = (0..big_n).map(|k| (k as f64 * 0.7).cos()).collect();
        let mean: Vec<f64> = (0..big_n * n).map(|k| (k as f64 * 0.2).cos()).collect();
        let cov: Vec<f64> = (0..big_n).flat_map(|_| [0.5, 0.1, 0.1, 0.4]).collect();
        // Nahi's update standardises with the filter's second moment.
        let second: Vec<f64> = (0..big_n).flat_map(|_| [1.5, 0.2, 0.2, 0.9]).collect();
        let moment = (update == Update::Linear && dropouts == Dropouts::Unknown)
            .then_some(second.as_slice());
        let mut t = 0;
        for _ in 0..22 {
            t += 1;
            check.step(t, &mean, &cov, moment, &y, &u).unwrap();
        }
        let count = allocations_in(|| {
            for _ in 0..2 {
                t += 1;
                check.step(t, &mean, &cov, moment, &y, &u).unwrap();
            }
        });
        assert_eq!(
            count, 0,
            "innovation check {dropouts:?} {update:?}: {count} allocations"
        );
    }

    // The streaming reader and the estimates writer, one and two threads.
    let (big_n, steps) = (5000, 6);
    let mut csv = String::from("t,i,y1\n");
    for t in 1..=steps {
        for i in 1..=big_n {
            csv += &format!("{t},{i},{}\n", (t * i) as f64 * 0.001 - 0.3);
        }
    }
    let layout = StepLayout::measurements(1);
    let x: Vec<f64> = (0..big_n * 2).map(|k| k as f64 / 3.0).collect();
    let p: Vec<f64> = (0..big_n * 4).map(|k| k as f64 / 7.0).collect();
    for threads in [1, 2] {
        let pool = started_pool(threads);
        pool.install(|| {
            let mut reader =
                StepReader::new("m.csv", csv.as_bytes(), layout.clone(), big_n).unwrap();
            let mut y = vec![0.0; big_n];
            reader.read_step(&mut y).unwrap();
            let mut steps_left = steps - 1;
            let count = allocations_in(|| {
                // Two steps per run, three runs: steps 2..=6 (the last run reads the end).
                for _ in 0..2 {
                    if steps_left > 0 {
                        reader.read_step(&mut y).unwrap();
                        steps_left -= 1;
                    }
                }
            });
            assert_eq!(count, 0, "reader, {threads} threads: {count} allocations");
            // With the arrival column of the mixture update and the NIS column.
            let columns = EstimatesColumns {
                predicted: false,
                n: 2,
                cross: 0,
                arrival: true,
                nis: true,
            };
            let pi: Vec<f64> = (0..big_n).map(|i| 1.0 / (1.0 + i as f64)).collect();
            let pi = RowValues {
                arrival: Some(pi.as_slice()),
                nis: Some(pi.as_slice()),
            };
            for format in [Format::Csv, Format::Json] {
                // Formatting on the caller's thread, and in parallel chunks on the pool.
                for parallel in [false, true] {
                    let mut writer = EstimatesWriter::new(std::io::sink(), format, columns, None)
                        .unwrap()
                        .parallel(parallel);
                    writer.write_step(1, &x, &p, None, pi).unwrap();
                    let mut t = 1;
                    let count = allocations_in(|| {
                        for _ in 0..2 {
                            t += 1;
                            writer.write_step(t, &x, &p, None, pi).unwrap();
                        }
                    });
                    assert_eq!(
                        count, 0,
                        "writer {format:?}, parallel {parallel}, {threads} threads: {count} allocations"
                    );
                }
                let writer = EstimatesWriter::new(std::io::sink(), format, columns, None).unwrap();
                let mut background = BackgroundWriter::new(writer, big_n);
                // Warm-up: the channels allocate a waker entry the first time each side
                // waits (the caller for a free batch, the thread for a full one), at moments
                // the thread's scheduling decides; let both wait once before counting.
                for t in 1..=4 {
                    background.write_step(t, &x, &p, None, pi).unwrap();
                }
                std::thread::sleep(std::time::Duration::from_millis(200));
                let mut t = 4;
                let count = allocations_in(|| {
                    for _ in 0..2 {
                        t += 1;
                        background.write_step(t, &x, &p, None, pi).unwrap();
                    }
                });
                background.finish().unwrap();
                assert_eq!(
                    count, 0,
                    "background writer {format:?}, {threads} threads: {count} allocations"
                );
            }
        });
    }
    // `evaluate` adds each run's sums (per filter 3·T numbers per step) as the run ends, in
    // run order: what it holds at its peak does not grow with the number of runs (it held
    // every run's sums, 96 KB each here, until the end).
    let long = model_of(3, 4000, "0.8", "");
    let inputs = sisfilt::inputs::RunInputs::of_model(&long).unwrap();
    let peak = |runs: usize| {
        let opts = sisfilt::evaluate::EvaluateOptions {
            filters: vec![sisfilt::evaluate::Compared::Distributed],
            ..sisfilt::evaluate::EvaluateOptions::new(runs, 1)
        };
        peak_bytes_in(|| {
            pool.install(|| {
                sisfilt::evaluate::evaluate(&long, &inputs, "alloc.toml", opts, || Ok(())).unwrap();
            });
        })
    };
    let (few, many) = (peak(8), peak(200));
    assert!(
        many < few + (1 << 20),
        "evaluate's peak: {few} bytes for 8 runs, {many} for 200"
    );
    memory_bounds_hold();
}

/// The bounds that `max_memory` is checked against before a filter is built
/// ([`JointFilter::bytes`], [`CentralizedFilter::bytes`]) hold what the filter allocates while it
/// is built and runs three steps, measured, for every band, moment and update, and are not
/// loose beyond 4×: a bound that is too small lets a size through to the allocator, one that is
/// too large refuses what fits.
///
/// The dense kernels of the lifted filters (faer) keep a packing scratch per thread, sized by the
/// processor's caches, allocated at the thread's first large product and kept: a few megabytes a
/// thread that do not grow with the chain, and not part of a filter's bound. The bounds are
/// measured on one thread that has done such a product.
fn memory_bounds_hold() {
    let pool = started_pool(1);
    pool.install(|| {
        let m = faer::Mat::<f64>::identity(256, 256);
        let mut out = faer::Mat::<f64>::zeros(256, 256);
        sisfilt::linalg::dense::product(
            out.as_mut(),
            faer::Accum::Replace,
            m.as_ref(),
            m.as_ref(),
            1.0,
        );
        memory_bounds_hold_on_this_thread();
    });
}

fn memory_bounds_hold_on_this_thread() {
    use sisfilt::filter::CentralizedFilter;
    let ratio = |peak: usize, bound: f64, what: &str| {
        assert!(
            bound >= peak as f64 && bound <= 4.0 * peak as f64,
            "{what}: bound {bound} bytes against {peak} measured"
        );
    };
    for big_n in [50, 200] {
        let model = model(big_n, "0.8", "");
        let y = vec![0.1; big_n];
        let u = vec![0.1; big_n];
        for (known, mixture) in [(false, false), (true, false), (false, true)] {
            let peak = peak_bytes_in(|| {
                let f = CentralizedFilter::new(&model, known, 1000).unwrap();
                let mut f: Box<dyn ChainFilter> = if mixture {
                    Box::new(f.with_mixture_update().unwrap())
                } else {
                    Box::new(f)
                };
                for _ in 0..3 {
                    f.step(&y, &u).unwrap();
                }
            });
            let what = format!("centralized, N = {big_n}, known {known}, mixture {mixture}");
            ratio(peak, CentralizedFilter::bytes(&model), &what);
        }
        for band in [2, 10, big_n - 1] {
            for (second_moment, dropouts, update) in [
                (SecondMoment::Band, Dropouts::Unknown, Update::Linear),
                (SecondMoment::Band, Dropouts::Known, Update::Linear),
                (SecondMoment::Lifted, Dropouts::Unknown, Update::Linear),
                (SecondMoment::Local, Dropouts::Unknown, Update::Linear),
                (SecondMoment::Band, Dropouts::Unknown, Update::Mixture),
            ] {
                let opts = JointOptions {
                    band,
                    second_moment,
                    dropouts,
                    update,
                    ..JointOptions::default()
                };
                let mut b = 0;
                let peak = peak_bytes_in(|| {
                    let mut f = JointFilter::new(&model, opts).unwrap();
                    b = f.a_eff_half_width();
                    for _ in 0..3 {
                        f.step(&y, &u).unwrap();
                    }
                });
                let what = format!("joint, N = {big_n}, {opts:?}");
                ratio(peak, JointFilter::bytes(&model, &opts, b), &what);
            }
        }
    }
}
