"""A fit in temporal shards over several GPUs or processes (docs/multi-gpu.md).

    pool     the CLI's rank processes, started before its own imports (imports no torch)
    rank     how the ranks start, what each does, how they stop
    shards   the plan of stretches, the merge, the joint refinement and the measurement
"""
