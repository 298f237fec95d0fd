"""Keyframes: the PerAct/RVT rule, the training samples it defines, and their annotation in episode files."""
