"""runtime.nodes: the processes of the runtime (robot_node, camera_node, policy_node); see runtime.launch.

Each node module has a config dataclass `CONFIG`, a `run(cfg, ctx) -> report` and `main()` for
`python -m runtime.nodes.<name> --config JSON`. None of them imports torch.
"""
