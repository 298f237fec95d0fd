"""Why does a policy fail? Analyses of a user's own evaluation journals, checkpoints, demos and tasks, each a
question with a table for an answer (`rvt2 diagnose NAME`, docs/DIAGNOSE.md):

- `target_choice`: which target a push went for (the colour tasks), from an evaluation journal;
- `oracle_gap`: which of the expert's keyframes a failing policy never reaches (policy and oracle journals);
- `instruction_swap`: does the instruction decide where the policy goes (checkpoint + demos);
- `phrasings`: where a phrasing the policy misreads moves its keyframes (checkpoint + demos);
- `paraphrase_neighbours`: whether the instruction encoder places each held-out paraphrase nearest its own variation (tasks);
- `stage2_blind`: where stage 2's zoomed box holds nothing to place the keyframe by (checkpoint + demos);
- `stage2_view`: what stage 2's box sees of the goal at each keyframe of insertion demos (demos);
- `insertion_stops`: where a policy's first insertion stops, pushed straight (evaluation journal);
- `precision_budget`: how precise a policy must be on a task (the oracle, degraded).

Each module is a library (`report`-like functions returning dicts, and `markdown`); `rvt2cli/cli/diagnose.py`
is the command line over them.
"""
