"""Batch runs: one pipeline over many inputs on Dask's distributed scheduler.

:func:`run_batch` expands the inputs (files, folders, globs), decides which ones are
already done (an output newer than both the input and the pipeline file is *skipped*
unless ``force``), and submits one task per remaining input to a ``dask.distributed``
cluster: a :class:`~distributed.LocalCluster` sized to the machine by default, or an
existing cluster given by its scheduler address. Each task (:func:`process_one`) reads
its input, runs the pipeline and writes ``DIR/<stem>.ply`` (``.npz`` when the pipeline
ends in a grid) atomically, and returns a small record; the data never passes through
the scheduler, so the inputs and the output folder must be on a filesystem the workers
share with the caller.

Failures stay per input: an error in one input's task gives it status ``failed`` with a one-line
message, and the others go on. A worker process that dies while running an input (killed, out of
memory) has that input rescheduled once on a live worker, and when it dies again the input is
reported ``failed`` with ``error_type`` ``"KilledWorker"`` (the local cluster's scheduler runs with
``distributed.scheduler.allowed-failures=1``; an existing cluster keeps its own setting, 3 by
default). No more inputs are in flight than the cluster has threads, so a dying worker only takes
down, and makes suspect, the inputs it was running, never inputs waiting in its queue; an input that
had finished but whose record was still held by the dying worker is recomputed, not failed. Dask's
``retries=1`` is also set on every task, for errors escaping the task function (which catches
recon's own errors itself, since rerunning a deterministic failure gains nothing).

An interruption (Ctrl-C: KeyboardInterrupt in the calling thread) cancels the running
tasks, records the unfinished inputs as ``interrupted`` in the summary, closes the local
cluster (its workers ignore SIGINT themselves, so a Ctrl-C to the whole process group
stops them through this process only), removes temporaries of cut-short writes and
re-raises; the outputs finished so far stay, and a rerun skips them.

``DIR/batch.json`` is the summary (also returned): per input ``status``, ``error``,
stage ``stages`` (each stage's report with ``seconds``), ``timings`` (read / pipeline /
write), ``peak_memory_mb`` (resident memory high-water mark of the worker process during
the task, see :func:`process_one`), ``input_stats`` and ``output_stats``
(``points`` / ``vertices`` / ``faces`` / ``grid_shape``).

Modules: :mod:`~recon_cli.batch.plan` (inputs, outputs, what is up to date),
:mod:`~recon_cli.batch.task` (one input in a worker), :mod:`~recon_cli.batch.cluster`
(the cluster, submission, collection, interruption).
"""

from __future__ import annotations

from recon_cli.batch.cluster import dask_setup, run_batch
from recon_cli.batch.plan import (
    INPUT_SUFFIXES,
    OUTPUT_SUFFIXES,
    STATUS_FAILED,
    STATUS_INTERRUPTED,
    STATUS_OK,
    STATUS_SKIPPED,
    SUMMARY_NAME,
    existing_output,
    expand_inputs,
    is_up_to_date,
    output_base,
    plan_batch,
    read_previous,
)
from recon_cli.batch.task import data_stats, process_one, register_stages, registered_stages

__all__ = [
    "dask_setup",
    "run_batch",
    "expand_inputs",
    "output_base",
    "existing_output",
    "is_up_to_date",
    "plan_batch",
    "read_previous",
    "INPUT_SUFFIXES",
    "OUTPUT_SUFFIXES",
    "SUMMARY_NAME",
    "STATUS_OK",
    "STATUS_FAILED",
    "STATUS_SKIPPED",
    "STATUS_INTERRUPTED",
    "register_stages",
    "registered_stages",
    "data_stats",
    "process_one",
]
