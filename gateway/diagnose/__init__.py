"""Offline diagnosis of mismatches between a recording and the nominal model.

``cdpr-gateway diagnose RECORDING --model MODEL.yaml --json REPORT.json [--report DIR]
[--validate OTHER]`` (spec/recording.md). Python API: :func:`engine.diagnose`.

Method
------
0. **Reference** (:func:`engine.reference_mode`): with ``tension_platform_i`` the residual
   is per cable (below); without it, with pose, mass and a geometry, it is the platform's
   wrench balance (:mod:`.wrench`, :mod:`.wrench_select`: no tension distribution assumed,
   per-cable effects identified jointly through the moving structure matrix).
1. **Simulate** the sensor reading of every cable from ``tension_platform_i`` (statics
   from pose and mass, :mod:`.platform`, only for ``mass_change``) and ``velocity_i`` with
   the nominal friction chain
   (:func:`gateway.model.chain.simulate`); residual ``r = measured - simulated``.
   A velocity column with white noise on it (a measured velocity logged in place of the
   setpoint) is put through a dead band of 4 noise standard deviations (the noise
   estimated from second differences; a clean setpoint is left alone), so that the
   simulated friction does not flip sign on noise while the cable stands still.
2. **Locate** (:mod:`.locate`): regimes per sample (reversal, rest, low/high speed,
   acceleration, steady) and contiguous regions where the smoothed residual energy is
   above twice its mean, with their share of the total residual energy.
3. **Split** the recording into ~1 s interleaved time blocks (10..40); even blocks train,
   odd blocks are held out, so both halves see every regime of a repeated motion.
4. **Select per cable** (:mod:`.select`), among the candidate effects of physics.md sec. 5
   that the columns allow (``mass_change`` needs pose, mass and a geometry), each a
   forward model built on :mod:`gateway.model` (:mod:`.forward`), fitted by bounded
   nonlinear least squares from grid / periodogram starting values (:mod:`.fit`):
   rounds of forward steps (best held-out candidate on top of those kept, lenient test;
   where no single candidate passes, the best pair of the four most promising ones, so
   that effects which cancel alone, e.g. an offset and a drift of opposite sign, are
   found; only while the held-out RMSE exceeds 1.1 times the noise), swaps (replace a
   kept effect by a better one) and a strict backward check; while
   the held-out RMSE stays above 3 times the white noise of the residual, a best-subset
   search over a short list (the kept effects and the three best others, subsets of up to
   two more effects, each fitted jointly) can undo an early greedy choice. In the check
   every kept effect must, against the model refitted without it, lower the held-out SSE
   by >= 0.3 % and by >= 4 standard errors of the noise of that decrease (estimated from
   held-out block sums), and differ from its nominal value by >= 4 standard errors.
   The first samples of each cable, until it has travelled 4 relaxation lengths
   ``F_R / sigma`` of the nominal chain (at most 10 % of the recording), are neither
   fitted nor scored: a recording may start in mid-motion with the friction state
   developed, while the simulation starts relaxed.
   Parameters are bounded physically: inertia >= 0, total viscous coefficient >= 0,
   Coulomb mu and f0 >= 0, gain > -0.9; a term that would need an impossible value sits at
   its bound, explains nothing and is not kept. A model without pulleys (a single-axis
   rig) gets one frictionless virtual pulley, so ``coulomb`` fits its ``f0`` alone.
   Saturated readings (a sensor clipped at its range: the column's extreme repeated in
   runs, :func:`.prepare.clipped_mask`) are excluded from fit and scores, counted per
   cable in the report's ``clipped`` and named in the summary.
   Long recordings (> 150 000 samples) are selected on evenly spread training blocks
   (with 1 s of warm-up each) and the result refitted on all training samples.
5. **Confusable rivals** (delay / lowpass / inertia, gain / coulomb, drift / offset): each
   kept one is swapped for its rivals and refitted; the evidence sentence says whether
   the held-out data separates them (>= 3 standard errors) or not.
6. **Validation** (``--validate``): every kept effect, with the parameters fitted here,
   must lower the error on the second recording against the model without it by 0.3 %
   and by 4 standard errors (block sums); the weakest that fails is dropped and the rest
   refitted, until all pass (:func:`.select.drop_unvalidated`).
7. **Report** (:mod:`.report`): effects gathered over the cables that kept them (one value
   per cable), ordered by the residual energy they explain in the final model (drop-one);
   RMSE before/after each finding, cumulatively, on all samples, the held-out blocks and
   the ``--validate`` recording (same parameters, never fitted there).
"""
