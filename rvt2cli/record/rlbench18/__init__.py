"""rvt2-18: RLBench's 18 tasks (the PerAct/RVT/RVT-2 set) rebuilt in ManiSkill 3 from primitive shapes and
articulations made in code. One module per task holds its environment and its scripted expert; importing
this package registers every environment (`make_env` does)."""

import importlib
import pkgutil

for _module in pkgutil.iter_modules(__path__):
    if _module.name != "base":
        importlib.import_module(f"{__name__}.{_module.name}")
