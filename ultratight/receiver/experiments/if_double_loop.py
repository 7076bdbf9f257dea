"""Seed 000's experiment: IF samples → correlators → prefilters → tight filter (the double loop).

The scenario schema, data cache and metrics are those of :mod:`ultratight.receiver.scenario_runner`
and :mod:`ultratight.receiver.scenario_config` (docs/ultratight.md); this module is the
:mod:`ultratight.receiver.experiments` entry for them. Its driver manages the on-disk cache of
generated IF, so ``run_scenario`` is called whole rather than through ``run_one``.
"""

from ultratight.receiver.engine import METHODS  # noqa: F401  (the accepted method names)

DEFAULT_METHODS = ("pb-kf-utc", "dlb-ukf", "dlb-ckf", "dlb-rackf")


def run_scenario(scenario, **kwargs):
    from ultratight.receiver.scenario_runner import run_scenario as _run
    return _run(scenario, **kwargs)
