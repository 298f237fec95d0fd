"""A cabinet of three drawers (bottom, middle, top) made of boxes, for open_drawer and put_item_in_drawer.

The cabinet's frame has its origin on the table under the middle of its front face, x pointing into the
cabinet (away from the robot) and z up. Each drawer slides out along -x on a prismatic joint whose
position is how far it is open (m). A vertical bar on each drawer's front is its handle, gripped from the
front and above with the fingers closing across the cabinet; a plinth lifts the bottom drawer off the table.
"""

import numpy as np
import sapien

DRAWERS = ("bottom", "middle", "top")          # RLBench's order (its variation index)
WIDTH, DEPTH = 0.26, 0.22                       # m: the cabinet's outer size across (y) and deep (x)
PLINTH = 0.06                                   # m: the cabinet stands on this
SLOT = 0.10                                     # m: the height of one drawer's slot
WALL = 0.01                                     # m: the thickness of the cabinet's and the drawers' walls
DRAWER_GAP = 0.005                              # m: a drawer's clearance in its slot, all round
DRAWER_TRAVEL = 0.19                            # m: how far a drawer opens
HANDLE_STANDOFF = 0.035                         # m: the handle bar's axis stands this far before the drawer's front
HANDLE_HALF = (0.008, 0.008, 0.03)              # m: the bar's half sizes (x deep, y across, z high)
HEIGHT = PLINTH + 3 * SLOT + 4 * WALL

BODY_COLOUR = (0.55, 0.42, 0.3, 1)
DRAWER_COLOUR = (0.75, 0.62, 0.45, 1)
HANDLE_COLOUR = (0.2, 0.2, 0.22, 1)


def slot_bottom(drawer: int) -> float:
    """The height of the floor of this drawer's slot (m, cabinet frame)."""
    return PLINTH + WALL + drawer * (SLOT + WALL)


def handle_centre(drawer: int) -> np.ndarray:
    """The middle of this drawer's handle bar, drawer closed (cabinet frame)."""
    return np.array([-HANDLE_STANDOFF, 0.0, slot_bottom(drawer) + SLOT / 2])


def inside_centre(drawer: int) -> np.ndarray:
    """The middle of this drawer's floor, drawer closed (cabinet frame)."""
    return np.array([DEPTH / 2, 0.0, slot_bottom(drawer) + DRAWER_GAP + WALL])


def _box(link, centre, half, colour):
    material = sapien.render.RenderMaterial(base_color=colour)
    link.add_box_collision(pose=sapien.Pose(centre), half_size=half)
    link.add_box_visual(pose=sapien.Pose(centre), half_size=half, material=material)


def build_cabinet(scene, name: str):
    """The cabinet as an articulation with a fixed root; its joints are DRAWERS, in order."""
    builder = scene.create_articulation_builder()
    builder.initial_pose = sapien.Pose([0.3, 0, 0])
    body = builder.create_link_builder()
    body.set_name("body")
    w, d = WIDTH / 2, DEPTH / 2
    _box(body, [d, 0, PLINTH / 2], [d, w, PLINTH / 2], BODY_COLOUR)                      # plinth
    _box(body, [DEPTH - WALL / 2, 0, HEIGHT / 2], [WALL / 2, w, HEIGHT / 2], BODY_COLOUR)  # back
    for side in (-1, 1):
        _box(body, [d, side * (w - WALL / 2), HEIGHT / 2], [d, WALL / 2, HEIGHT / 2], BODY_COLOUR)
    for shelf in range(4):                                                               # floors and the top
        z = PLINTH + WALL / 2 + shelf * (SLOT + WALL)
        _box(body, [d, 0, z], [d, w - WALL, WALL / 2], BODY_COLOUR)

    inner_w = w - WALL - DRAWER_GAP          # a drawer's outer half width
    inner_d = d - WALL / 2 - DRAWER_GAP      # ...half depth (its front flush with the cabinet's)
    inner_h = SLOT / 2 - DRAWER_GAP          # ...half height
    for index, label in enumerate(DRAWERS):
        drawer = builder.create_link_builder(body)
        drawer.set_name(f"{label}_drawer")
        z0 = slot_bottom(index) + DRAWER_GAP     # the drawer's underside
        _box(drawer, [inner_d, 0, z0 + WALL / 2], [inner_d, inner_w, WALL / 2], DRAWER_COLOUR)   # floor
        for x in (WALL / 2, 2 * inner_d - WALL / 2):                                             # front, back
            _box(drawer, [x, 0, z0 + inner_h], [WALL / 2, inner_w, inner_h], DRAWER_COLOUR)
        for side in (-1, 1):
            _box(drawer, [inner_d, side * (inner_w - WALL / 2), z0 + inner_h], [inner_d, WALL / 2, inner_h],
                 DRAWER_COLOUR)
        bar = handle_centre(index)
        _box(drawer, bar, HANDLE_HALF, HANDLE_COLOUR)
        for side in (-1, 1):                                                                     # the bar's posts
            post_half = [(HANDLE_STANDOFF - HANDLE_HALF[0]) / 2, 0.005, 0.005]
            _box(drawer, [-post_half[0], 0, bar[2] + side * (HANDLE_HALF[2] - 0.005)], post_half, HANDLE_COLOUR)
        drawer.set_joint_name(f"{label}_drawer_joint")
        # the joint's axis is its frame's x: turned half round, positive positions pull the drawer out
        turned = sapien.Pose(q=[0, 0, 0, 1])
        drawer.set_joint_properties("prismatic", limits=[[0.0, DRAWER_TRAVEL]], pose_in_parent=turned,
                                    pose_in_child=turned, friction=0.0, damping=1.0)
    return builder.build(name, fix_root_link=True)
