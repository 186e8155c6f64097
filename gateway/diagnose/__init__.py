"""Offline diagnosis of mismatches between a recording and the nominal model.

``cdpr-gateway diagnose RECORDING --model MODEL.yaml --json REPORT.json [--report DIR]
[--validate OTHER] [--write-model FITTED.yaml]`` (docs/recording-format.md). Python API:
:func:`fromfiles.diagnose_file` (files: read, reference, statics, one or several
recordings), :func:`engine.diagnose` (a recording in memory, with either reference:
:class:`reference.PlatformReference`, :class:`wrench_reference.WrenchReference`).

One way through, five stages (:mod:`.engine` reads as them):

1. **Prepare** (:mod:`.prepare`, the reference's ``prepare``): rows with every value, the
   nominal chain, per-cable series (a noisy velocity column through a dead band), clipped
   readings, ~1 s interleaved time blocks (10..40; even blocks train, odd ones are held
   out, so both halves see every regime of a repeated motion), the warm-up of the friction
   state after the start and after every gap, the candidates each cable's motion can show
   (each effect module's ``needs_motion`` / ``applicable``; a platform effect needs pose,
   mass and a geometry), a subset of a long recording (> 150 000 samples per cable).
2. **Locate** (:mod:`.locate`): regimes per sample and the regions where the nominal
   model's residual concentrates.
3. **Select** (:mod:`.selection`): one selector over the reference's units, a strategy it is
   given: one :class:`.reference.CableUnit` per cable (the reading against the nominal chain
   run from the platform tension, :mod:`.forward`, :mod:`.fit`), or one
   :class:`.wrench_unit.WrenchUnit` for the platform's wrench balance (every cable at once
   through the moving structure matrix; no tension distribution assumed). Forward steps,
   pairs, swaps, a strict backward check, a best-subset search while the held-out residual
   holds more than noise, nested and rival checks.
4. **Fit** (:mod:`.reference`, :mod:`.significance`): the selection refitted on every
   training sample, checked on the ``--validate`` recording, then kept only by
   significance: every candidate x unit tested on held-out blocks (Student t over the
   blocks), Benjamini-Hochberg over all of them, and the effect's presence against its
   spread across time blocks (:mod:`.stats`).
5. **Report** (:mod:`.report`, :mod:`.evidence`, :mod:`.signals`, :mod:`.plots`): findings
   ordered by the residual energy they explain (drop-one), each with its tests, both
   standard errors and the alternatives held-out data cannot tell from it; where the final
   residual lives; and what it depends on beyond the catalogue (``unexplained``).
"""
