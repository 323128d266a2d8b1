"""The simulator library: the world contract (contract.py), the PyBullet reference backend
(bullet_world.py), the fast batched backend (fast_world.py + fast_kernels.py), scenario actors
(actors.py) and traffic drivers (traffic.py). The sim service (services/sim), training and
evaluation import it; it imports only racecav.common."""
