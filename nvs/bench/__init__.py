"""The benchmark: run time, memory and FLOPs of the model options at the studies' sizes, beside the authors' code.

``measure`` (interleaved timing, FLOPs, peak memory), ``contenders`` (an nvs model option in an execution mode, or
the authors' code), ``reference`` (their code imported from the path given), ``run`` (one image size),
``report`` (Markdown), ``profile`` (torch.profiler of a training step); ``__main__`` is the CLI
(``python -m nvs.bench``).
"""

