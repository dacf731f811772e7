"""Multiple regression of the tool-tip deviation on sensor features, by streamed QR.

The compensation model of the paper (section 3, eq. 12-13) is a multiple linear regression of a
TTP deviation component (dx, dy, dz) on FBG elongations and temperatures, tuned by "stepwise
regression with ANOVA"; Table 1 reports its coefficients and standard errors. This package is the
numerical engine behind that: ordinary least squares that is accurate on ill-conditioned designs
(it passes the NIST StRD linear reference problems, Filip and Wampler included, streamed in
chunks of any size) and that streams a 36 h campaign of any length in constant memory.

Mathematics
-----------
Let ``A = [X | Y]`` (n x (p+k)): the design X exactly as given (the caller adds a column of ones
for an intercept) next to the k targets. Each column is divided by a fixed scale ``s`` (the
column's RMS in the first chunk, rounded to a power of two so that the division is exact), and
the scaled matrix is reduced to its triangular factor ``R`` (``A_s = Q R``) by Householder QR,
chunk by chunk: ``R <- qr([R; A_chunk])`` (the "TSQR" reduction). The normal equations are never
formed, so the condition number is not squared.

Because ``R^T R = A_s^T A_s``, every least-squares problem on a subset S of the columns of X and
one target j is solved *exactly* from ``R`` alone: the QR factor of the (p+k) x (|S|+1) matrix
``R[:, S + [p+j]]`` is the QR factor of ``A_s[:, S + [p+j]]``. Its leading |S| x |S| triangle
``T`` and last column ``z`` give the scaled coefficients ``T b = z``, and the square of its last
diagonal entry is the residual sum of squares. Sub-models, the ANOVA table and the whole stepwise
search therefore never re-read the data.

Precision
---------
Householder QR in double precision is backward stable: the computed factor is exact for data
perturbed by about one rounding unit u per column, so coefficients carry a relative error of
about ``kappa * u`` (kappa: condition number of the scaled design). That is 1e-12 for a typical
compensation design (eq. 12 with raw temperatures: kappa ~ 1e3) but only 1e-7 for NIST Filip
(kappa ~ 5e9), whatever the chunking. ``R`` is therefore kept in double-double arithmetic (an
unevaluated sum ``hi + lo`` of two doubles, ~32 significant digits): merges of triangles,
sub-model factors and triangular solves are always done in it (they are tiny), and the data pass
itself is done in it too when the scaled design is ill-conditioned (kappa > 1e6) or has fewer
than 2(p+k) rows so far (``precision="auto"``). Otherwise the data pass is LAPACK Householder QR
(``geqrf``) on the stacked ``[R; chunk]``, in cache-sized blocks.

Gram fast path: when the design is well conditioned, forming ``X^T X`` costs far less than QR
(one BLAS ``syrk`` pass, at the speed of the Gram/Cholesky recipe) and loses nothing that
matters. So after the first 1024 rows (QR), ``precision="auto"`` adds each chunk through its Gram
and a Cholesky of ``R^T R + G``, and keeps the result only if the equilibrated condition number of
the new factor's design part is <= 500 and each target's norm is <= 300 times its residual's
(``KAPPA_GRAM``, ``RESID_RATIO_GRAM`` in :mod:`~fbgcomp.models.regression.gram`: calibrated
to keep >= 7.3 correct digits in the worst coefficient, see their notes); otherwise the same
rows go through QR as above (``gram_rows_`` counts the rows that took the Gram). Every NIST
StRD design stays on QR.

Inference follows the textbook (and statsmodels) formulas: ``sigma^2 = SSR / (n - |S|)``,
``Cov(b) = sigma^2 (X^T X)^-1 = sigma^2 T^-1 T^-T`` (through the triangular inverse, then
unscaled), Student-t tests and intervals, and the overall F test with R^2 centred when the model
holds a constant column and uncentred otherwise. Those assume independent errors; for
autocorrelated ones (slow drifts sampled every second) an accumulator created with
``hac_lags`` also keeps lagged score sums, and results and stepwise tests then use the
Newey-West (HAC) sandwich, statsmodels' ``cov_type="HAC"`` (see :class:`QRAccumulator`);
``cov_type="nonrobust"`` selects the naive formulas.

Modules
-------
:mod:`~fbgcomp.models.regression.accumulator`: :class:`QRAccumulator` (the streamed factor),
:func:`accumulate_series` and :func:`ols`; :mod:`~fbgcomp.models.regression.fit`: fits read
from the factor (:func:`ols_from_factor`); :mod:`~fbgcomp.models.regression.results`:
:class:`OLSResults`; :mod:`~fbgcomp.models.regression.stepwise`: :func:`stepwise`;
:mod:`~fbgcomp.models.regression.hac`: the Newey-West statistics;
:mod:`~fbgcomp.models.regression.gram`: the Gram fast path;
:mod:`~fbgcomp.models.regression.doubledouble`: double-double arithmetic;
:mod:`~fbgcomp.models.regression.factor`: rank and conditioning tests of a triangular factor.
"""

from fbgcomp.models.regression.accumulator import QRAccumulator, accumulate_series, ols
from fbgcomp.models.regression.factor import RankDeficientError
from fbgcomp.models.regression.fit import ols_from_factor
from fbgcomp.models.regression.hac import COV_TYPES, HAC_MAX_LAG, andrews_bartlett_lags, hac_lag_grid
from fbgcomp.models.regression.results import OLSResults
from fbgcomp.models.regression.stepwise import StepwiseResult, stepwise

__all__ = [
    "COV_TYPES",
    "HAC_MAX_LAG",
    "OLSResults",
    "QRAccumulator",
    "RankDeficientError",
    "StepwiseResult",
    "accumulate_series",
    "andrews_bartlett_lags",
    "hac_lag_grid",
    "ols",
    "ols_from_factor",
    "stepwise",
]
