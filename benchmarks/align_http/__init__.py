"""``POST /align`` latency and throughput over real HTTP, beside the engine's own time.

``python -m benchmarks.align_http [--references 40 1000] [--json out.json] [--accuracy]``

The default run needs the runtime packages alone (``pip install -e .``: numpy, scipy,
onnxruntime, httpx): no pybullet, open3d or torch. ``--accuracy`` also needs pybullet's meshes
(the ``train`` extra).

For each size the service runs as a real process (``python -m service``, started by
``evaluation.served.ServiceProcess``) on a free loopback port with a data directory of its own,
seeded before it starts. 40 references are the first 40 of the shipped gallery
(``models/gallery.npz``); a larger size adds the other shipped ones, then padding references.
Where onnxruntime offers CUDA, each size is measured with the CUDA execution provider beside the
CPU one (``--providers``). One module a job:

- ``clouds``: the requests, resampled clouds of the shipped references in random poses;
- ``padding``: the padding references of a larger gallery, computed once and cached;
- ``timing``: latency, throughput, registrations and the classifier's refit, over HTTP and in
  this process, and the growth with the gallery's size;
- ``accuracy``: success shares on pybullet's meshes (``--accuracy``);
- ``report``: the figures as a table;
- ``command``: the command line, which runs them in turn.

Every count is fixed and the run stops by itself; nothing leaves loopback. The figures are
printed (targets of issue 12 marked PASS or FAIL, on whatever machine it ran) and, with
``--json``, written. The model comes from ``--model`` / ``--gallery`` or ``DPC_MODEL__PATH`` /
``DPC_MODEL__GALLERY``; other ``DPC_*`` variables (engine settings) reach the served process and
the in-process engine alike.
"""
