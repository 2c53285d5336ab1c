"""Inverse problems written against the public API: material estimation (``estimation``), motion control
(``control``, its optimisers in ``controllers``, the seed's throw in ``throw``), gripper control (``grippers``), the
seed's scenes built in code (``scenes``), the algorithms both use (``optim``, ``lockstep``) and batches of runs
(``jobs``). Their loss kernels are in ``warpcloth.kernels.losses``.
"""
