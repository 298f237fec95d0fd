"""Where a phase's time goes: the wall seconds and calls of its named steps.

Each step is one or more functions, named where the code looks them up ("module", "name" or
"module", "Class.method"); while a `PartTimer` is open they are wrapped with a clock. A step that calls
itself counts once; a timer opened again adds to its totals. Unlike cProfile this costs nothing in the code between the steps, and it reads the
same on every Python: under Python 3.12's cProfile most of these functions went missing from the stats.
"""

import functools
import importlib
import time


class PartTimer:
    def __init__(self, parts: dict[str, list[tuple[str, str]]]):
        self.parts = parts
        self.seconds = {name: 0.0 for name in parts}
        self.calls = {name: 0 for name in parts}
        self._depth = {name: 0 for name in parts}
        self._saved = []

    def _wrap(self, part: str, function):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            self._depth[part] += 1
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self._depth[part] -= 1
                if self._depth[part] == 0:
                    self.seconds[part] += time.perf_counter() - start
                    self.calls[part] += 1
        return timed

    def __enter__(self):
        for part, targets in self.parts.items():
            for module, name in targets:
                owner = importlib.import_module(module)
                *path, attribute = name.split(".")
                for step in path:
                    owner = getattr(owner, step)
                original = owner.__dict__[attribute] if isinstance(owner, type) else getattr(owner, attribute)
                self._saved.append((owner, attribute, original))
                setattr(owner, attribute, self._wrap(part, original))
        return self

    def __exit__(self, *exc):
        for owner, attribute, original in reversed(self._saved):
            setattr(owner, attribute, original)
        self._saved.clear()
        return False
