"""Recording: task scenes in ManiSkill/SAPIEN with the camera rig, scripted experts, episodes written to MCAP."""
