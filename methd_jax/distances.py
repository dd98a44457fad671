"""The thesis's distances around a user (§4.2.1, Table 4.1), one home for every config that uses
them: the rewards (:class:`envs.rewards.SafetyConfig`), the environments' visible users, the
evaluation engine, the pictures and, through the exported manifest, the robot's safety layer."""

COLLISION_DISTANCE = 1.37
"""d_coll: robot centre to user closer than this is a collision (the base's 0.77 m enclosing radius
plus 0.6 m), m."""
CRITICAL_DISTANCE = 1.77
"""d_crit: inside it the robot is in the user's critical zone (p_c of eq. 4.11), m."""
USER_RADIUS = 0.25
"""A user's body as a disc: for contacts with the base's footprint in the evaluation and for the
leg-height cylinders a LiDAR sees, m."""
