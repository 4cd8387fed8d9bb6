"""The simulator (issue 3): a seeded MAGIC urban phase in PyBullet, the robots' bodies and
sensors, the contest's rules and the radio (paper sections 2, 3.1, 4.3).

Modules, one per concern:

- :mod:`sim.world_generator` -- ``WorldConfig`` (``configs/world/*.yaml``) -> ``World``;
- :mod:`sim.ground_truth` -- 10 cm layers (vertical structures, drivability, reachable area);
- :mod:`sim.robot_body` -- kinematic skid-steer bodies on the terrain (slip, curbs, battery);
- :mod:`sim.scene` / :mod:`sim.ray_worker` -- PyBullet bodies, batched ray casts, rendering;
- :mod:`sim.lidar`, :mod:`sim.camera`, :mod:`sim.imu`, :mod:`sim.apriltag` -- the sensors;
- :mod:`sim.actors` -- people walking patrol routes;
- :mod:`sim.rules` -- triggers, blasts, laser and visual-lock neutralization, events;
- :mod:`sim.radio_model` -- link quality, relays, the shared capacity;
- :mod:`sim.simulator` -- ``Simulator`` and its in-process ``RobotDriver`` (``SimDriver``);
- :mod:`sim.server` -- ``magic sim``: the simulator over zenoh.

Ground truth never leaves ``sim/`` except to ``mission/`` evaluation (DESIGN section 2).
"""
