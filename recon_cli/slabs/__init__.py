"""Work in slabs: the plumbing the stages that cut a cloud into slabs share.

- :mod:`.plan`: how many slabs a run takes for its memory, where the seams go, which sub-slab a
  point is in;
- :mod:`.runners`: where the slabs' steps run (this process, with their states spilled to files
  between steps when the memory asks for it, or a Dask cluster), one progress bar over a job,
  each step's figures.

Used by ``recon_cli.stages.poisson.distributed`` and ``recon_cli.stages.normals.distributed``,
through these public names only.
"""
