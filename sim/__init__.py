"""The simulated world: UR5e/UR5 + Robotiq 2F-85 on a table, tasks, domain randomization and sim twins.

`sim/` is the lowest floor of sudd: it imports nothing from datagen/, policy/, runtime/ or safety/.
"""

import os

# MuJoCo picks its GL backend when it is first imported: headless EGL unless the user chose (osmesa, glfw).
os.environ.setdefault("MUJOCO_GL", "egl")
