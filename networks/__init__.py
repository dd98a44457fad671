"""Flax modules only: the thesis's actor-critic (SU, NavRL) and GuideRL networks."""

from networks.actor_critic import ActorCritic, GuidePolicy, LidarEncoder, count, policy_count

__all__ = ["ActorCritic", "GuidePolicy", "LidarEncoder", "count", "policy_count"]
