"""racecav: emergency collision avoidance for 1/10-scale cars (PPO policy, MPC-APF baseline, Zenoh services)."""
__version__ = "0.1.0"
