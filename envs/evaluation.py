"""A trained policy as a positioning method of the evaluation engine (:mod:`methd_jax.evaluation`).

:class:`Policy` runs an SU policy, or NavRL with its goal from a GuideRL policy, in the engine's
Chase behaviour. Each step it builds the environment's world from the engine's context and calls
the environment's own goal update, observation and action mapping, so the policy sees exactly what
it saw in training.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from envs.nav import NavEnv, World
from methd_jax import robot as robot_lib
from methd_jax.deploy.safety import SafetyConfig
from methd_jax.evaluation import safety_layer
from methd_jax.evaluation.methods import Chase, Context
from methd_jax.geometry import rotate, to_local


@struct.dataclass
class PolicyState:
    actions: jax.Array  # (3, 3) a_{t-1}, a_{t-2}, a_{t-3}
    velocity: jax.Array  # (3,) base velocity at the previous step (for the acceleration term)
    u_w: jax.Array  # () GuideRL's user weight
    guide_actions: jax.Array  # (2,) GuideRL's previous actions
    step: jax.Array  # () int32 the engine step of the last call (-2 before the first)


class Policy:
    """A trained policy in Chase: SU (one user), or NavRL with GuideRL choosing its goal (two users).

    ``env`` is the :class:`NavEnv` the policy was trained on, rebuilt with the evaluation's
    trajectories and floor (it supplies the exact observation and action mapping of training);
    ``policy(obs) -> action`` is deterministic (see :func:`train.export.load`). For NavRL the env
    carries the GuideRL policy as its ``guide_policy``.
    """

    multi_user = True

    def __init__(self, env: NavEnv, policy, name: str = "DRL", safety: SafetyConfig | None = None):
        """``safety``: put the deployment's safety layer (:mod:`.safety_layer`, the JAX twin of
        :class:`methd_jax.deploy.safety.CollisionMonitor`) between the policy and the base."""
        self.env = env
        self.policy = policy
        self.name = name
        self.safety = safety
        if env.config.num_users == 2 and env.guide_policy is None:
            raise ValueError("a two-user (NavRL) policy needs a GuideRL policy for its goal")

    def init(self):
        return PolicyState(jnp.zeros((3, 3)), jnp.zeros(3), jnp.float32(0.0), jnp.zeros(2), jnp.int32(-2))

    def resume(self, state: PolicyState, ctx: Context) -> PolicyState:
        """``state`` with the base's own motion as its action and velocity history where the engine
        drove the base since the last call (Escape, Inform, a request's Haptic, or a carried-over
        base moving as its episode begins). Training never has that gap: a history of seconds ago
        gives a one-step acceleration of the whole change since (tens of m/s^2) and blends actions
        that pointed wherever the policy drove before, often at the user it escaped from; the
        navigator likewise ramps from the base's velocity when it takes over from a policy."""
        velocity = robot_lib.velocity(ctx.robot)
        moving = jnp.broadcast_to(jnp.clip(velocity / self.env.action_scale, -1.0, 1.0), state.actions.shape)
        gap = ctx.step != state.step + 1
        return state.replace(
            actions=jnp.where(gap, moving, state.actions),
            velocity=jnp.where(gap, velocity, state.velocity),
        )

    def idle(self, state: PolicyState, ctx: Context) -> PolicyState:
        """A step the engine drives the base: GuideRL goes on watching the users, as the deployed
        GuideRL node does whatever drives the base, so that its goal is current when Chase resumes."""
        if self.env.config.num_users != 2:
            return state
        u_w, guide_actions = self.env.guide_step(ctx.users, state.u_w, state.guide_actions)
        return state.replace(u_w=u_w, guide_actions=guide_actions)

    def observe(self, state: PolicyState, ctx: Context) -> tuple[PolicyState, World, jax.Array]:
        """(``state`` resumed, the environment's world at this step, the policy's raw observation):
        the first half of :meth:`chase`."""
        state = self.resume(state, ctx)
        k_goal, k_obs = jax.random.split(ctx.key)
        u = self.env.config.num_users
        world = World(
            robot=ctx.robot,
            floor=ctx.floor,
            users=jnp.zeros(u, jnp.int32),
            t=jnp.int32(0),
            start=jnp.int32(0),
            request_step=jnp.int32(2**30),  # the engine's Haptic behaviour handles the request
            requester=jnp.int32(0),
            actions=state.actions[1:],
            velocity=state.velocity,
            held=jnp.float32(0.0),
            goal=jnp.zeros(3),
            u_w=state.u_w,
            goal_target=jnp.float32(0.0),
            guide_actions=state.guide_actions,
            pending=jnp.zeros((0, 3)),
            dynamics=jnp.ones(2),
            contacts=jnp.int32(0),
            key=ctx.key,
        )
        world = self.env.update_goal(world, ctx.users, k_goal, scripted_step=True)
        obs, _, _ = self.env.observe(world, state.actions[0], k_obs, ctx.users)
        return state, world, obs

    def act(self, state: PolicyState, ctx: Context, world: World, action: jax.Array):
        """(the next state, the :class:`Chase` order) for ``action`` in [-1, 1]^3 taken in the
        ``state`` and ``world`` of :meth:`observe`: the second half of :meth:`chase`."""
        command = self.env.command(action, state.actions[:2])
        if self.safety is not None:
            users_xy = ctx.users["pose"][:, :2]
            command = safety_layer.filter_command(
                command,
                ctx.scan,
                to_local(ctx.pose, users_xy),
                rotate(-ctx.pose[2], ctx.users["vel_world"][:, :2]),
                ctx.present,
                self.env.config.safety.collision_distance,
                self.safety,
                robot_lib.velocity(ctx.robot),
            )
        new = PolicyState(
            actions=jnp.concatenate([action[None], state.actions[:2]]),
            velocity=robot_lib.velocity(ctx.robot),
            u_w=world.u_w,
            guide_actions=world.guide_actions,
            step=ctx.step,
        )
        return new, Chase(command, world.goal, jnp.bool_(False))

    def chase(self, state: PolicyState, ctx: Context):
        state, world, obs = self.observe(state, ctx)
        return self.act(state, ctx, world, jnp.clip(self.policy(obs), -1.0, 1.0))
