"""Published baselines retrained in the same harness (``model=tatarchenko|chen|sun``), and what they share in ``common``.

Each network has the same ``forward(batch, needs) -> outputs`` as ``NVSNet`` and lists the extras it can compute in
``provides``: a loss that needs another extra stops the build (``nvs.run.build.check_needs``), and one that reads an output
the baseline lacks stops at its first read (``BaselineOutputs``), each with one message naming the model, the output
and the way out.
"""
