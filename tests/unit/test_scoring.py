"""Score functions: top-k, leave-one-out top-k, Mahalanobis (Sec. IV-A, supp:score-fn-analysis)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from services.embedding.detector.detections import p_values
from services.embedding.detector.scoring import (
    MahalanobisModel,
    ScoringError,
    loo_topk_scores,
    topk_score,
)

# ---------------------------------------------------------------- top-k


def test_topk_score_hand_computed() -> None:
    sims = np.array([[0.9, 0.7, 0.5], [0.2, 0.1, -0.3]])
    # k=1: -max            -> [-0.9, -0.2]
    np.testing.assert_allclose(topk_score(sims, 1), [-0.9, -0.2])
    # k=2: -(0.9+0.7)/2 = -0.8 ; -(0.2+0.1)/2 = -0.15
    np.testing.assert_allclose(topk_score(sims, 2), [-0.8, -0.15])
    # k=3: -(0.9+0.7+0.5)/3 = -0.7 ; -(0.2+0.1-0.3)/3 = 0
    np.testing.assert_allclose(topk_score(sims, 3), [-0.7, 0.0], atol=1e-15)


def test_top1_is_minus_max_cosine_of_sec_iv_a() -> None:
    cache = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    query = np.array([2.0, 1.0])
    # cosines: 2/sqrt5, 1/sqrt5, 3/(sqrt5*sqrt2) = 3/sqrt10 (the largest)
    cos = cache @ query / (np.linalg.norm(cache, axis=1) * np.linalg.norm(query))
    sims = np.sort(cos)[::-1][None, :]
    assert topk_score(sims, 1)[0] == pytest.approx(-round(3 / math.sqrt(10), 4), abs=1e-12)


def test_topk_score_float32_input_and_rounding_slack() -> None:
    sims = np.array([[1.0000001, 0.5]], dtype=np.float32)
    out = topk_score(sims, 2)
    assert out.dtype == np.float64
    assert out[0] == pytest.approx(-0.75, abs=1e-6)


def test_the_same_text_embedded_in_two_batches_ties_with_itself() -> None:
    # the bundled model gives "the loading bay" a similarity of 1.0 to its copies in one
    # batch and 1.0000002 (or 0.9999998) to a copy embedded alone: a nominal text seen
    # again must tie with its calibration scores, whichever way the noise falls
    calibration = topk_score(np.array([[1.0, 1.0], [1.0, 0.5]]), 1)
    for noisy in (1.0000002, 0.9999998, 0.99999994):
        again = topk_score(np.array([[noisy, 0.5]], dtype=np.float32), 1)
        assert again[0] == calibration[0]
        assert p_values(calibration, again)[0] == 1.0
    # and a mean over k of noisy similarities too
    assert topk_score(np.array([[0.8000001, 0.6999999]]), 2)[0] == \
        topk_score(np.array([[0.8, 0.7]]), 2)[0]


@pytest.mark.parametrize("k", [0, -1, 4])
def test_topk_score_bad_k(k: int) -> None:
    with pytest.raises(ScoringError) as err:
        topk_score(np.array([[0.9, 0.8, 0.7]]), k)
    assert err.value.field == "k"
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize(
    "sims",
    [
        np.array([0.9, 0.8]),  # 1-D
        np.array([[0.5, 0.9]]),  # not sorted descending
        np.array([[0.9, -3.4028235e38]]),  # FAISS padding for a missing result
        np.array([[2.5, 1.0]]),  # not a cosine (an L2 distance?)
        np.array([[np.nan, 0.1]]),
    ],
)
def test_topk_score_bad_similarities(sims: np.ndarray) -> None:
    with pytest.raises(ScoringError) as err:
        topk_score(sims, 1)
    assert err.value.field == "similarities"


# ---------------------------------------------------------------- leave-one-out top-k


def test_loo_topk_hand_computed_duplicates_and_ties() -> None:
    # Searched with k+1 = 3 neighbours, k = 2. Cache ids 10..16; 13 is an exact
    # duplicate of 11; 14, 15, 16 are three copies of the vector of 12.
    sims = np.array(
        [
            [1.0, 0.8, 0.6],  # id 10: own entry first (the usual case)
            [1.0, 1.0, 0.8],  # id 11: duplicate 13 ties and comes FIRST
            [1.0, 1.0, 1.0],  # id 12: three ties pushed own id out of the results
            [1.0, 1.0, 0.8],  # id 13: own entry second
        ]
    )
    labels = np.array(
        [
            [10, 11, 12],
            [13, 11, 10],
            [14, 15, 16],
            [11, 13, 10],
        ],
        dtype=np.int64,
    )
    self_labels = np.array([10, 11, 12, 13], dtype=np.int64)
    expected = [
        -(0.8 + 0.6) / 2,  # drop col 0 (id 10)                     -> -0.7
        -(1.0 + 0.8) / 2,  # drop col 1 (id 11); duplicate 13 stays  -> -0.9
        -(1.0 + 1.0) / 2,  # own absent: drop last col               -> -1.0
        -(1.0 + 0.8) / 2,  # drop col 1 (id 13); duplicate 11 stays  -> -0.9
    ]
    np.testing.assert_allclose(loo_topk_scores(sims, labels, self_labels, 2), expected)


def test_loo_topk_removes_own_label_not_column_zero() -> None:
    # An approximate index (or float32 rounding) ranks another id above the
    # member itself: own id 20 sits in column 1.
    sims = np.array([[0.99, 0.98, 0.5]])
    labels = np.array([[21, 20, 22]])
    # correct: drop id 20 -> -(0.99 + 0.5)/2 = -0.745 ; column-0 drop would give -0.74
    out = loo_topk_scores(sims, labels, np.array([20]), 2)
    assert out[0] == pytest.approx(-0.745)
    assert out[0] != pytest.approx(-0.74)


def test_loo_topk_extra_columns_and_k1() -> None:
    sims = np.array([[1.0, 0.7, 0.6, 0.1]])
    labels = np.array([[5, 3, 4, 9]])
    # k=1 with 4 columns: drop id 5, top-1 of [0.7, 0.6, 0.1] = 0.7
    assert loo_topk_scores(sims, labels, np.array([5]), 1)[0] == pytest.approx(-0.7)
    # k=3: -(0.7+0.6+0.1)/3
    assert loo_topk_scores(sims, labels, np.array([5]), 3)[0] == pytest.approx(-1.4 / 3)


def test_loo_topk_with_faiss_matches_brute_force() -> None:
    faiss = pytest.importorskip("faiss")
    rng = np.random.default_rng(0)
    x = rng.normal(size=(8, 6)).astype(np.float32)
    x[5] = x[2]  # an exact duplicate under another id
    x[7] = x[2]  # and another
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    ids = np.arange(100, 108, dtype=np.int64)
    index = faiss.IndexIDMap(faiss.IndexFlatIP(x.shape[1]))
    index.add_with_ids(x, ids)
    k = 3
    sims, labels = index.search(x, k + 1)
    got = loo_topk_scores(sims, labels, ids, k)
    # brute force: cosines (rounded to 4 decimals) to every OTHER member, mean of the k largest
    gram = np.round(x.astype(np.float64) @ x.astype(np.float64).T, 4)
    want = [-np.sort(np.delete(gram[i], i))[::-1][:k].mean() for i in range(len(x))]
    np.testing.assert_allclose(got, want, atol=1e-6)
    # the duplicates of member 2 score -1 for k <= 2 (two identical others remain)
    dup = loo_topk_scores(*index.search(x, 3), ids, 2)
    np.testing.assert_allclose(dup[[2, 5, 7]], -1.0, atol=1e-6)


def test_loo_topk_bad_inputs() -> None:
    sims = np.array([[1.0, 0.8, 0.6]])
    labels = np.array([[10, 11, 12]])
    own = np.array([10])
    cases = [
        ((sims, np.array([[10, 11, -1]]), own, 2), "labels"),  # FAISS padding
        ((sims, labels.astype(float), own, 2), "labels"),
        ((sims, labels[:, :2], own, 2), "labels"),
        ((sims, labels, np.array([10, 11]), 2), "self_labels"),
        ((sims, labels, own, 3), "k"),  # needs k+1 = 4 columns
        ((sims, labels, own, 0), "k"),
        ((sims[:, ::-1], labels, own, 2), "similarities"),
    ]
    for args, field in cases:
        with pytest.raises(ScoringError) as err:
            loo_topk_scores(*args)
        assert err.value.field == field, args


# ---------------------------------------------------------------- Mahalanobis

LINE = np.array([[0.0], [1.0], [2.0], [3.0], [4.0]])


def test_mahalanobis_hand_computed_1d() -> None:
    # mean 2; scatter M = 4+1+0+1+4 = 10; S = 10/4 = 2.5; nu = 2.5/1;
    # Sigma = 0.9*2.5 + 0.1*2.5 = 2.5 ; precision 0.4
    m = MahalanobisModel.fit(LINE, shrinkage=0.1)
    assert m.mean == pytest.approx([2.0])
    assert m.nu == pytest.approx(2.5)
    np.testing.assert_allclose(m.precision, [[0.4]])
    assert m.n == 5 and m.dim == 1
    # |7-2|/sqrt(2.5) = sqrt(10); |2-2| = 0
    np.testing.assert_allclose(m.score(np.array([[7.0], [2.0]])), [math.sqrt(10), 0.0])


def test_mahalanobis_loo_hand_computed_1d() -> None:
    # lambda=0.1, nu=2.5 kept fixed.
    # x=4 out: [0,1,2,3], mean 1.5, S = (2.25+.25+.25+2.25)/3 = 5/3,
    #   Sigma = .9*5/3 + .1*2.5 = 1.75, d^2 = 2.5^2/1.75 = 25/7.
    #   closed form: u=2, A = .9*10/3 + .25 = 3.25, c = .9*5/(4*3) = .375,
    #   q = 4/3.25 = 16/13, 1-cq = 7/13, d^2 = (5/4)^2 (16/13)/(7/13) = 25/7.
    # x=3 out: [0,1,2,4], mean 1.75, M = 8.75, Sigma = .9*8.75/3 + .25 = 2.875,
    #   d^2 = 1.25^2/2.875 = 25/46.
    # x=2 out: mean stays 2 -> 0. By symmetry x=0 ~ x=4 and x=1 ~ x=3.
    m = MahalanobisModel.fit(LINE, shrinkage=0.1)
    a, b = math.sqrt(25 / 7), math.sqrt(25 / 46)
    np.testing.assert_allclose(m.loo_scores(LINE), [a, b, 0.0, b, a], atol=1e-12)


def test_mahalanobis_score_matches_explicit_numpy_formula() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(20, 5)) @ rng.normal(size=(5, 5)) + 3.0
    queries = rng.normal(size=(7, 5))
    lam = 0.3
    s = np.cov(x, rowvar=False)  # (n-1) normalisation
    nu = np.trace(s) / 5
    sigma = (1 - lam) * s + lam * nu * np.eye(5)
    z = queries - x.mean(axis=0)
    want = np.sqrt(np.diag(z @ np.linalg.inv(sigma) @ z.T))
    m = MahalanobisModel.fit(x, shrinkage=lam)
    np.testing.assert_allclose(m.score(queries), want, rtol=1e-10)
    np.testing.assert_allclose(m.precision @ sigma, np.eye(5), atol=1e-10)
    np.testing.assert_allclose(m.sample_covariance, s, rtol=1e-12)
    assert m.nu == pytest.approx(nu)


@pytest.mark.parametrize(
    ("n", "d", "lam"),
    [(12, 4, 0.0), (12, 4, 0.1), (12, 4, 0.5), (12, 4, 1.0), (8, 20, 0.2), (4, 2, 0.5)],
)
def test_mahalanobis_loo_closed_form_equals_brute_force_refit(n: int, d: int, lam: float) -> None:
    rng = np.random.default_rng(n * 100 + d)
    x = rng.normal(size=(n, d)) * rng.uniform(0.5, 3.0, size=d)
    m = MahalanobisModel.fit(x, shrinkage=lam)
    # refit without x_i, same shrinkage and the full-data nu, then score x_i
    refits = [MahalanobisModel.fit(np.delete(x, i, axis=0), lam, nu=m.nu) for i in range(n)]
    brute = np.array([refit.score(x[i : i + 1])[0] for i, refit in enumerate(refits)])
    np.testing.assert_allclose(m.loo_scores(x), brute, rtol=1e-9)
    # leaving a point out makes it look farther than scoring it in-sample
    assert np.all(m.loo_scores(x) >= m.score(x) - 1e-12)


def test_mahalanobis_loo_singular_without_the_point_is_inf() -> None:
    # lambda=0, n = d+1: Sigma is fine, but without any one point the two left
    # span a line the removed point is off -> infinite distance.
    x = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    m = MahalanobisModel.fit(x, shrinkage=0.0)
    assert np.all(np.isinf(m.loo_scores(x)))


def test_mahalanobis_is_frozen_and_read_only() -> None:
    m = MahalanobisModel.fit(LINE)
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.n = 3  # type: ignore[misc]
    with pytest.raises(ValueError):
        m.mean[0] = 1.0


def test_mahalanobis_bad_inputs() -> None:
    rng = np.random.default_rng(2)
    x = rng.normal(size=(6, 3))
    cases = [
        (lambda: MahalanobisModel.fit(x[:2]), "size"),
        (lambda: MahalanobisModel.fit(x, shrinkage=-0.1), "shrinkage"),
        (lambda: MahalanobisModel.fit(x, shrinkage=1.5), "shrinkage"),
        (lambda: MahalanobisModel.fit(x, nu=-1.0), "nu"),
        (lambda: MahalanobisModel.fit(x[0]), "vectors"),
        (lambda: MahalanobisModel.fit(np.where(x > 1, np.nan, x)), "vectors"),
        (lambda: MahalanobisModel.fit(np.ones((5, 3)), shrinkage=0.5), "covariance"),
        (lambda: MahalanobisModel.fit(x[:3], shrinkage=0.0), "covariance"),  # n <= d
        (lambda: MahalanobisModel.fit(x).score(np.zeros((2, 4))), "vectors"),
        (lambda: MahalanobisModel.fit(x).loo_scores(x[:5]), "vectors"),
        (lambda: MahalanobisModel.fit(x).loo_scores(x + 1.0), "vectors"),
    ]
    for make, field in cases:
        with pytest.raises(ScoringError) as err:
            make()
        assert err.value.field == field
