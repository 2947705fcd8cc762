//! The block-band operations of docs/theory.md §8 (`sisfilt::linalg::band`) against dense nalgebra on random
//! symmetric positive definite matrices (seeded), for many shapes including `nb = 1, 2`,
//! `k = 0`, `k = nb − 1` and block sizes 1–5 (5 exercises the unspecialised kernels).

use nalgebra::DMatrix;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sisfilt::linalg::band::{
    BandCholesky, BandError, CompletionWorkspace, GenBand, SandwichWorkspace, SymBand,
    completion_precision, sandwich,
};

/// `(nb, bs, k)` shapes for the symmetric operations.
const SHAPES: &[(usize, usize, usize)] = &[
    (1, 1, 0),
    (1, 3, 0),
    (2, 2, 0),
    (2, 2, 1),
    (2, 1, 1),
    (3, 4, 1),
    (5, 1, 0),
    (5, 2, 2),
    (5, 3, 4),
    (6, 1, 5),
    (7, 4, 2),
    (8, 2, 3),
    (9, 2, 1),
    (6, 5, 2),
];

fn uniform(rows: usize, cols: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
    DMatrix::from_fn(rows, cols, |_, _| rng.random_range(-1.0..=1.0))
}

/// A dense SPD matrix with correlations between all blocks: `G Gᵀ + n/4 I`.
fn random_spd(n: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
    let g = uniform(n, n, rng);
    &g * g.transpose() + DMatrix::identity(n, n) * (n as f64 / 4.0 + 0.1)
}

/// A symmetric block-banded matrix of bandwidth `k`, positive definite by strict diagonal
/// dominance.
fn random_band_spd(nb: usize, bs: usize, k: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
    let n = nb * bs;
    let mut a = uniform(n, n, rng);
    for r in 0..n {
        for c in 0..n {
            if (r / bs).abs_diff(c / bs) > k {
                a[(r, c)] = 0.0;
            }
        }
    }
    let mut a = &a + a.transpose();
    for r in 0..n {
        let off: f64 = a.row(r).iter().map(|v| v.abs()).sum::<f64>() - a[(r, r)].abs();
        a[(r, r)] = off + 0.5;
    }
    a
}

/// `max |x − y| / max |y|` on the blocks `|i − j| ≤ w`.
fn band_rel_err(x: &DMatrix<f64>, y: &DMatrix<f64>, bs: usize, w: usize) -> f64 {
    let (mut err, mut scale) = (0.0f64, 0.0f64);
    for r in 0..y.nrows() {
        for c in 0..y.ncols() {
            if (r / bs).abs_diff(c / bs) <= w {
                err = err.max((x[(r, c)] - y[(r, c)]).abs());
                scale = scale.max(y[(r, c)].abs());
            }
        }
    }
    err / scale
}

/// The band `|i − j| ≤ w` of a dense matrix, zero outside.
fn band_of(a: &DMatrix<f64>, bs: usize, w: usize) -> DMatrix<f64> {
    DMatrix::from_fn(a.nrows(), a.ncols(), |r, c| {
        if (r / bs).abs_diff(c / bs) <= w {
            a[(r, c)]
        } else {
            0.0
        }
    })
}

/// Every block of `s` set to NaN, standing for stale content an operation must overwrite.
fn poison(s: &mut SymBand) {
    for i in 0..s.nb() {
        for d in 0..=s.width().min(s.nb() - 1 - i) {
            s.block_mut(i, d).fill(f64::NAN);
        }
    }
}

/// Storage slots past the last block column are zero: rebuilding from the dense form gives
/// the identical struct.
fn assert_clean(s: &SymBand) {
    assert_eq!(
        *s,
        SymBand::from_dense(&s.to_dense(), s.bs(), s.width()),
        "nonzero slot outside the matrix"
    );
}

#[test]
fn dense_round_trips_and_band_copies() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let a = random_spd(12, &mut rng);
    let s = SymBand::from_dense(&a, 3, 2);
    assert_eq!((s.nb(), s.bs(), s.width()), (4, 3, 2));
    assert_eq!(s.to_dense(), band_of(&a, 3, 2));
    assert_eq!(s.block(1, 2)[1 + 2 * 3], a[(3 + 1, 9 + 2)]);
    assert_eq!(
        SymBand::zeros(3, 2, 9).width(),
        2,
        "width clamped to nb − 1"
    );
    let mut narrow = SymBand::zeros(4, 3, 1);
    narrow.copy_band_from(&s);
    assert_eq!(narrow.to_dense(), band_of(&a, 3, 1));
    let mut wide = SymBand::zeros(4, 3, 3);
    wide.copy_band_from(&narrow);
    assert_eq!(wide.to_dense(), band_of(&a, 3, 1));
    assert_clean(&wide);

    let g = uniform(12, 12, &mut rng);
    let gb = GenBand::from_dense(&g, 2, 2);
    assert_eq!((gb.nb(), gb.bs(), gb.half_width()), (6, 2, 2));
    assert_eq!(gb.to_dense(), band_of(&g, 2, 2));
    assert_eq!(gb.block(3, 1)[1], g[(7, 2)]);
    assert_eq!(GenBand::zeros(3, 2, 9).half_width(), 2);
}

#[test]
fn completion_precision_inverse_matches_band_and_is_banded() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for &(nb, bs, k) in SHAPES {
        let n = nb * bs;
        let s = random_spd(n, &mut rng);
        // P given wider than k: only its band k may enter.
        let p = SymBand::from_dense(&s, bs, (k + 1).min(nb - 1));
        let mut lambda = SymBand::zeros(nb, bs, k);
        poison(&mut lambda);
        let mut ws = CompletionWorkspace::new(nb, bs, k + 1);
        completion_precision(&p, k, &mut lambda, &mut ws).unwrap();
        assert_eq!(lambda.width(), k);
        assert_clean(&lambda);
        let dense = lambda.to_dense();
        // Banded by construction: to_dense carries nothing outside |i − j| ≤ k.
        assert_eq!(dense, band_of(&dense, bs, k));
        let completion = dense.clone().try_inverse().expect("Λ invertible");
        let err = band_rel_err(&completion, &s, bs, k);
        assert!(err < 1e-10, "(nb, bs, k) = {:?}: {err:e}", (nb, bs, k));
        // Λ is symmetric positive definite.
        assert!((&dense - dense.transpose()).amax() == 0.0);
        assert!(dense.clone().cholesky().is_some());
        if k == nb - 1 {
            let inv = s.clone().try_inverse().unwrap();
            assert!((&dense - &inv).amax() < 1e-10 * inv.amax());
        }
        if k == 0 {
            for i in 0..nb {
                let blk = s.view((i * bs, i * bs), (bs, bs)).into_owned();
                let inv = blk.try_inverse().unwrap();
                let got = dense.view((i * bs, i * bs), (bs, bs));
                assert!((got - &inv).amax() < 1e-12 * inv.amax());
            }
        }
    }
}

#[test]
fn completion_precision_names_the_first_clique_that_is_not_positive_definite() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for &(nb, bs, k) in SHAPES {
        let s = random_spd(nb * bs, &mut rng);
        let j0 = rng.random_range(0..nb - k);
        let mut p = SymBand::from_dense(&s, bs, k);
        // Block (j0, j0+k) lies in clique j0 only (for k = 0 it is the diagonal block j0).
        let blk = p.block_mut(j0, k);
        if k == 0 {
            blk.iter_mut().for_each(|v| *v = -*v);
        } else {
            blk[0] = 100.0 * s.amax();
        }
        // Reference: the first clique whose dense block fails nalgebra's Cholesky.
        let pd = p.to_dense();
        let m = (k + 1) * bs;
        let expect = (0..nb - k)
            .find(|&j| {
                let c = pd.view((j * bs, j * bs), (m, m)).into_owned();
                c.cholesky().is_none()
            })
            .expect("some clique fails");
        assert_eq!(expect, j0);
        let mut lambda = SymBand::zeros(nb, bs, k);
        let mut ws = CompletionWorkspace::new(nb, bs, k);
        let err = completion_precision(&p, k, &mut lambda, &mut ws).unwrap_err();
        assert_eq!(
            err,
            BandError::CliqueNotPositiveDefinite {
                first: expect,
                last: expect + k
            }
        );
    }
    let e = BandError::CliqueNotPositiveDefinite { first: 2, last: 4 };
    assert_eq!(
        e.to_string(),
        "clique of blocks 3..5 is not positive definite"
    );
}

#[test]
fn cholesky_solve_matches_dense_solve() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for &(nb, bs, k) in SHAPES {
        let a = random_band_spd(nb, bs, k, &mut rng);
        let mut chol = BandCholesky::new(nb, bs, k);
        chol.factor(&SymBand::from_dense(&a, bs, k)).unwrap();
        // The factor reproduces A.
        let mut l = DMatrix::zeros(nb * bs, nb * bs);
        for j in 0..nb {
            for i in j..(j + k + 1).min(nb) {
                let blk = DMatrix::from_column_slice(bs, bs, chol.l_block(i, j));
                l.view_mut((i * bs, j * bs), (bs, bs)).copy_from(&blk);
            }
        }
        assert!((&l * l.transpose() - &a).amax() < 1e-12 * a.amax());
        for _ in 0..3 {
            let rhs = uniform(nb * bs, 1, &mut rng);
            let expect = a.clone().lu().solve(&rhs).unwrap();
            let mut x = rhs.as_slice().to_vec();
            chol.solve_in_place(&mut x);
            let err = (DMatrix::from_column_slice(nb * bs, 1, &x) - &expect).amax();
            assert!(err < 1e-11 * expect.amax(), "{:?}: {err:e}", (nb, bs, k));
        }
    }
}

#[test]
fn cholesky_names_the_first_pivot_that_is_not_positive_definite() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for &(nb, bs, k) in SHAPES {
        let mut a = random_band_spd(nb, bs, k, &mut rng);
        let q = rng.random_range(0..nb);
        // Lowering the diagonal of block q leaves the leading minors before it unchanged.
        for r in q * bs..(q + 1) * bs {
            a[(r, r)] -= 10.0 * a.amax();
        }
        // Reference: the first leading block minor that is not positive definite.
        let expect = (0..nb)
            .find(|&i| {
                let n = (i + 1) * bs;
                a.view((0, 0), (n, n)).into_owned().cholesky().is_none()
            })
            .unwrap();
        assert_eq!(expect, q);
        let mut chol = BandCholesky::new(nb, bs, k);
        let err = chol.factor(&SymBand::from_dense(&a, bs, k)).unwrap_err();
        assert_eq!(err, BandError::PivotNotPositiveDefinite { block: q });
    }
    let e = BandError::PivotNotPositiveDefinite { block: 0 };
    assert_eq!(
        e.to_string(),
        "Cholesky pivot block 1 is not positive definite"
    );
}

#[test]
fn selected_inverse_matches_dense_inverse_on_every_width() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    for &(nb, bs, k) in SHAPES {
        let a = random_band_spd(nb, bs, k, &mut rng);
        let inv = a.clone().try_inverse().unwrap();
        let mut chol = BandCholesky::new(nb, bs, k);
        chol.factor(&SymBand::from_dense(&a, bs, k)).unwrap();
        for w in k..nb {
            let mut out = SymBand::zeros(nb, bs, w);
            poison(&mut out);
            chol.selected_inverse(&mut out);
            assert_clean(&out);
            let err = band_rel_err(&out.to_dense(), &inv, bs, w);
            assert!(
                err < 1e-12,
                "(nb, bs, k, w) = {:?}: {err:e}",
                (nb, bs, k, w)
            );
        }
    }
}

#[test]
fn selected_inverse_of_the_completion_precision_extends_the_band() {
    // Update steps 3 → 6 with Φ = 0: the band k comes back, and beyond it the Gauss–Markov
    // continuation, i.e. the dense inverse of Λ.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for &(nb, bs, k) in SHAPES {
        let s = random_spd(nb * bs, &mut rng);
        let p = SymBand::from_dense(&s, bs, k);
        let mut lambda = SymBand::zeros(nb, bs, k);
        completion_precision(&p, k, &mut lambda, &mut CompletionWorkspace::new(nb, bs, k)).unwrap();
        let mut chol = BandCholesky::new(nb, bs, k);
        chol.factor(&lambda).unwrap();
        let w = nb - 1;
        let mut out = SymBand::zeros(nb, bs, w);
        chol.selected_inverse(&mut out);
        assert!(band_rel_err(&out.to_dense(), &s, bs, k) < 1e-10);
        let completion = lambda.to_dense().try_inverse().unwrap();
        assert!(band_rel_err(&out.to_dense(), &completion, bs, w) < 1e-10);
    }
}

#[test]
fn sandwich_matches_dense_product_band() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let cases: &[(usize, usize, usize, usize)] = &[
        // (nb, bs, k, b)
        (1, 2, 0, 0),
        (1, 1, 0, 3),
        (2, 2, 1, 1),
        (2, 3, 0, 1),
        (3, 1, 2, 0),
        (6, 2, 2, 1),
        (9, 2, 2, 3),
        (5, 3, 0, 2),
        (12, 1, 2, 4),
        (7, 4, 1, 2),
        (4, 2, 3, 5),
        (20, 2, 2, 3),
        (6, 5, 1, 1),
    ];
    for &(nb, bs, k, b) in cases {
        let n = nb * bs;
        let s = random_spd(n, &mut rng);
        let a = GenBand::from_dense(&uniform(n, n, &mut rng), bs, b);
        let (k, b) = (k.min(nb - 1), b.min(nb - 1));
        let ad = a.to_dense();
        let expect = band_of(&(&ad * &s * ad.transpose()), bs, k);
        let wp = (k + 2 * b).min(nb - 1);
        // A workspace built for a wider A and band serves this one too.
        let mut ws = SandwichWorkspace::new(nb, bs, b + 2, k + 1);
        for width in [wp, nb - 1] {
            let p = SymBand::from_dense(&s, bs, width);
            let mut out = SymBand::zeros(nb, bs, k);
            poison(&mut out);
            sandwich(&a, &p, &mut out, &mut ws);
            assert_clean(&out);
            let got = out.to_dense();
            let err = band_rel_err(&got, &expect, bs, k);
            assert!(
                err < 1e-12,
                "(nb, bs, k, b) = {:?}: {err:e}",
                (nb, bs, k, b)
            );
        }
    }
}
