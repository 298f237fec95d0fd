"""rvt2: RVT-2 (Goyal et al.) as a toolkit.

Data flows through the subpackages in this order:
record -> data (MCAP episodes) -> keyframes -> render -> model -> train -> eval -> export.
"""

__version__ = "0.1.0"
