"""The keyframe rule on synthetic trajectories, one edge case at a time."""

import numpy as np

from rvt2cli.keyframes.rule import (KeyframeParams, find_keyframes, ignore_collisions, next_keyframe_index,
                                    observation_starts)

P = KeyframeParams(stop_velocity=0.02, pause_velocity=0.02, stop_buffer=4, obs_every=10)


def trajectory(n, moving_spans, gripper_changes=()):
    """Arm speed 0.5 rad/s inside the half-open spans, 0 elsewhere; the gripper toggles at the given frames."""
    speed = np.zeros(n)
    for a, b in moving_spans:
        speed[a:b] = 0.5
    velocities = np.zeros((n, 9))
    velocities[:, 3] = speed
    gripper = np.ones(n, dtype=bool)
    for f in gripper_changes:
        gripper[f:] = ~gripper[f:]
    return gripper, velocities


def frames(keyframes):
    return [(k.frame, k.reasons) for k in keyframes]


def test_arm_arriving_at_rest_is_a_keyframe_and_last_frame_too():
    gripper, vel = trajectory(60, [(5, 20), (30, 45)])
    assert frames(find_keyframes(gripper, vel, P)) == [(20, ("stopped",)), (45, ("stopped",)), (59, ("last",))]


def test_resting_at_the_start_is_not_a_keyframe():
    gripper, vel = trajectory(40, [(10, 20)])
    assert [k.frame for k in find_keyframes(gripper, vel, P)] == [20, 39]


def test_gripper_change_is_a_keyframe_and_blocks_rest_nearby():
    gripper, vel = trajectory(60, [(5, 20), (30, 45)], gripper_changes=[21])
    # the arm arrives at 20, but the gripper changes at 21 (inside the window): only the gripper keyframe
    assert frames(find_keyframes(gripper, vel, P)) == [(21, ("gripper",)), (45, ("stopped",)), (59, ("last",))]


def test_debounce_blocks_a_second_rest_keyframe_within_the_buffer():
    gripper, vel = trajectory(60, [(5, 20), (21, 22), (30, 40)])
    # arrives at 20 and again at 22 (two frames later): the second is debounced
    assert [k.frame for k in find_keyframes(gripper, vel, P)] == [20, 40, 59]
    assert [k.frame for k in find_keyframes(gripper, vel, KeyframeParams(stop_buffer=1))] == [20, 22, 40, 59]


def test_keyframe_just_before_the_last_frame_is_dropped():
    gripper, vel = trajectory(30, [(5, 28)], gripper_changes=[28])
    # gripper keyframe at 28 is adjacent to the last frame 29: only the last remains
    assert frames(find_keyframes(gripper, vel, P)) == [(29, ("last",))]


def test_second_to_last_frame_is_never_a_rest_keyframe():
    gripper, vel = trajectory(30, [(5, 28)])
    assert [k.frame for k in find_keyframes(gripper, vel, P)] == [29]


def test_slow_motion_above_threshold_is_not_rest():
    gripper, vel = trajectory(40, [(5, 30)])
    vel[20:25, 3] = 0.05  # slows down but keeps moving faster than 0.02
    assert [k.frame for k in find_keyframes(gripper, vel, P)] == [30, 39]


def test_observation_starts_and_next_keyframe():
    gripper, vel = trajectory(60, [(5, 20), (30, 45)])
    kfs = find_keyframes(gripper, vel, P)
    starts = observation_starts(60, kfs, obs_every=10)
    assert starts == [0, 10, 20, 30, 40, 45, 50]
    assert [kfs[next_keyframe_index(f, kfs)].frame for f in starts] == [20, 20, 45, 45, 45, 59, 59]


def test_ignore_collisions_marks_motions_that_make_new_contact():
    gripper, vel = trajectory(60, [(5, 20), (30, 45)])
    kfs = find_keyframes(gripper, vel, P)  # 20, 45, 59
    contacts = [[] for _ in range(60)]
    for t in range(21, 30):     # contact already there as the motion to 45 begins: not new
        contacts[t] = ["table"]
    for t in range(50, 55):     # new contact on the way to 59
        contacts[t] = ["box"]
    assert ignore_collisions(contacts, kfs) == [False, False, True]


def test_a_pause_between_chained_motions_is_a_keyframe_at_its_slowest_frame():
    # a scripted expert chains two motions: the arm slows to 0.03 rad/s (never below 0.02) and goes on
    speed = np.concatenate([np.linspace(0, 0.5, 10), np.linspace(0.5, 0.09, 10), [0.06, 0.04, 0.03, 0.035, 0.07],
                            np.linspace(0.2, 0.5, 10), np.linspace(0.5, 0.0, 10), np.zeros(5)])
    velocities = np.zeros((len(speed), 7))
    velocities[:, 0] = speed
    gripper = np.ones(len(speed), dtype=bool)
    kfs = find_keyframes(gripper, velocities)  # the default rule: pausing below 0.05, stopped below 0.02
    assert [k.frame for k in kfs][:2] == [22, 44]  # the pause's slowest frame (0.03), then where the arm stops
    # the stop threshold alone (the rule without pauses) misses it
    assert 22 not in [k.frame for k in find_keyframes(gripper, velocities, KeyframeParams(pause_velocity=0.02))]


def test_a_slow_down_that_does_not_pause_is_no_keyframe():
    speed = np.concatenate([np.linspace(0, 0.3, 10), [0.2, 0.12, 0.09, 0.12, 0.2], np.linspace(0.2, 0.0, 10), np.zeros(3)])
    velocities = np.zeros((len(speed), 7))
    velocities[:, 0] = speed
    # the slow-down makes no keyframe; the arm stops at 24, which the last frame (27) stands for
    assert [k.frame for k in find_keyframes(np.ones(len(speed), dtype=bool), velocities)] == [27]


def test_an_arrival_just_before_the_gripper_acts_or_the_end_is_merged_into_that_keyframe():
    speed = np.concatenate([np.linspace(0, 0.3, 10), np.linspace(0.3, 0.0, 10), np.zeros(10),
                            np.linspace(0, 0.3, 10), np.linspace(0.3, 0.0, 10), np.zeros(8)])
    velocities = np.zeros((len(speed), 7))
    velocities[:, 0] = speed
    gripper = np.ones(len(speed), dtype=bool)
    gripper[22:] = False  # closes 3 frames after the arm stops (frame 19)
    frames = [k.frame for k in find_keyframes(gripper, velocities)]
    assert 19 not in frames and 22 in frames  # the grasp stands for the arrival
    gripper[:] = True
    gripper[29:] = False  # closes 10 frames after it: two keyframes
    assert [19, 29] == [k.frame for k in find_keyframes(gripper, velocities)][:2]


def test_merge_refinements_keeps_the_last_of_a_chain_of_small_corrections():
    from rvt2cli.keyframes.rule import KeyframeEvent, merge_refinements

    # pre-insert, then corrections of 25, 10, 3 and 1 mm, then a 120 mm insertion (the expert's insert_peg)
    frames = [10, 20, 30, 40, 50, 60]
    x = np.cumsum([0.0, 0.025, 0.010, 0.003, 0.001, 0.120])
    positions = np.zeros((61, 7))
    positions[:, 6] = 1.0  # x y z qx qy qz qw: no turn
    for f, xi in zip(frames, x):
        positions[f, 0] = xi
    events = [KeyframeEvent(f, ("stopped",)) for f in frames[:-1]] + [KeyframeEvent(60, ("last",))]
    assert merge_refinements(events, positions, 0.0) == events
    assert [k.frame for k in merge_refinements(events, positions, 0.030)] == [50, 60]
    assert [k.frame for k in merge_refinements(events, positions, 0.005)] == [10, 20, 50, 60]
    grasp = [KeyframeEvent(10, ("stopped",)), KeyframeEvent(20, ("gripper",))]   # a grasp is never merged away
    assert merge_refinements(grasp, positions, 0.030) == grasp
    turned = positions.copy()
    turned[50, 3:] = [0.0, 0.0, np.sin(np.radians(18)), np.cos(np.radians(18))]  # 36 degrees about z, 1 mm away
    assert [k.frame for k in merge_refinements(events, turned, 0.030)] == [40, 50, 60]  # a turn in place stays
