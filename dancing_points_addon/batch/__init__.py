"""Headless batch conversion: a folder of takes in, baked duets out, on every core.

``python -m dancing_points_addon batch IN... -o OUT_DIR --format blend|fbx|bvh|npz``
and, inside Blender, ``blender --background --command dancing_points convert ...``
(``operators/batch_cli.py``) both take :func:`add_arguments` and run :func:`run`:

* :mod:`.plan`: the input files (``.csv``, ``.bvh``, ``.amc``, ``.fbx``; an FBX
  take goes to a worker with Blender's ``bpy``, which reads it with Blender's
  importer), one output per take named after it (never one of the inputs), the
  temporary names the workers write;
* :mod:`.lock`: one batch at a time per output folder (a second one is refused);
* :mod:`.scheduler`: the parent, running ``--jobs`` worker processes
  (:mod:`.worker`, talking :mod:`.messages`), committing finished outputs,
  stopping on Ctrl-C;
* :mod:`.progress`: the progress bar (stderr) and a result line per file (stdout),
  in the order the files finish (the report keeps the input order);
* :mod:`.report`: the JSON report and the summary line;
* :mod:`.options`: formats, exit statuses, the options a job carries;
* :mod:`.cluster`: ``--cluster``, the same batch with the takes run as Dask
  tasks on a cluster's workers (Dask imported only then).

Before any work the command line is checked (inputs, the networks loaded once
with :func:`~..nets.check_models`, the report path, the output folder's lock):
a problem there is one line and exit status 2. Then a bad file is reported and
skipped, the rest go on; the exit status is 1 if any file failed. ``--jobs`` is
capped at the number of files, with a warning line when above the cores. The
package never imports ``bpy``: the Blender side hands its converter to the worker loop (:func:`.worker.worker_main`).
"""
from __future__ import annotations

import argparse
import datetime
import os
import sys
import time

from ..argtypes import (EXIT_BAD_INPUT, EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_TERMINATED,
                        add_audio_arguments, add_calibration_arguments, height_metres, positive_float,
                        positive_int, printable, thread_count)
from ..errors import InputError, one_line
from .options import (BPY_FORMATS, BPY_INPUTS, CORE_INPUTS, FORMATS, check_rigs, default_jobs, input_needs_bpy,
                      job_options, resolve_model_dir)
from .lock import LOCK_NAME
from .lock import acquire as acquire_lock
from .plan import (PART, check_not_inputs, discover, make_output_dirs, output_bases, output_kinds, output_paths, plan,
                   remove_empty_dirs, remove_stale_temps, remove_temps, stale_temps, temp_leftovers, temp_path)
from .progress import Progress, eta, fmt_duration, result_line
from .report import REPORT_NAME, build_report, check_report_path, is_report, summary_line, write_report
from .scheduler import Batch
from .cluster_connect import cluster_spec

__all__ = ["add_arguments", "run",
           "FORMATS", "BPY_FORMATS", "CORE_INPUTS", "BPY_INPUTS", "REPORT_NAME", "PART", "LOCK_NAME",
           "discover", "output_bases", "output_kinds", "output_paths", "plan", "temp_path", "temp_leftovers",
           "remove_temps", "stale_temps", "remove_stale_temps", "is_report",
           "Progress", "eta", "fmt_duration"]


def add_arguments(p: argparse.ArgumentParser, default_format: str = "npz") -> None:
    """The batch options (shared by the ``batch`` subcommand and Blender's ``convert``)."""
    from ..nets import MODEL_ENV

    p.add_argument("inputs", nargs="+", metavar="IN",
                   help="take files (.csv), BVH (.bvh), CMU AMC (.amc) or FBX (.fbx, read by Blender's bpy) "
                        "files, or folders searched recursively for them")
    p.add_argument("-o", "--output-dir", required=True, metavar="OUT_DIR",
                   help="folder for the outputs (created if missing)")
    p.add_argument("--format", choices=FORMATS, default=default_format,
                   help=f"output format (default {default_format}): npz = SPEC §4 arrays, bvh = "
                        "NAME_leader.bvh + NAME_follower.bvh, blend = a scene with the baked duet, "
                        "fbx = the two skinned armatures with their animation")
    p.add_argument("-j", "--jobs", type=positive_int, default=None, metavar="N",
                   help=f"worker processes (default: the number of cores, {default_jobs()} here; never more "
                        f"than the files; a warning when more than the cores); with --cluster: at most N "
                        f"takes at once on the cluster (default: as many as its worker threads)")
    p.add_argument("--cluster", type=cluster_spec, default=None, metavar="ADDRESS",
                   help="run the takes as Dask tasks on a Dask cluster: the scheduler's address "
                        "(tcp://HOST:8786), or local:N for N worker processes on this machine; needs "
                        "the dask and distributed packages (not bundled with the extension) and the same "
                        "version of this project and models on every worker (README: Batch on a cluster)")
    p.add_argument("--render", action="store_true",
                   help="also render a Workbench preview video NAME.mp4 (needs Blender's bpy)")
    existing = p.add_mutually_exclusive_group()  # replace or skip: one answer to an existing output
    existing.add_argument("--overwrite", action="store_true",
                          help="replace existing outputs (never an input), and a --report file that is not a "
                               "report")
    existing.add_argument("--resume", action="store_true",
                          help="skip the takes whose outputs already exist (e.g. after an interrupted run)")
    p.add_argument("--report", default=None, metavar="PATH",
                   help=f"JSON report (default: OUT_DIR/{REPORT_NAME}); replaces an earlier report, never "
                        f"an input; another existing file only with --overwrite")
    p.add_argument("--models", default=None, metavar="DIR",
                   help=f"folder with the ONNX models (default: ${MODEL_ENV}, else the bundled models/)")
    p.add_argument("--threads", type=thread_count, default=1, metavar="N",
                   help="onnxruntime threads per worker (default 1, at most 64)")
    p.add_argument("--input-fps", type=positive_float, default=None, metavar="F",
                   help="override every input's frame rate")
    p.add_argument("--asf", default=None, metavar="PATH",
                   help="ASF skeleton for the AMC inputs (default: found beside each)")
    p.add_argument("--height", type=height_metres, default=None, metavar="H",
                   help="the tracked dancer's height in metres (default: each take's height_m, else estimated)")
    add_calibration_arguments(p)
    add_audio_arguments(p)
    p.add_argument("--no-foot-lock", action="store_true", help="turn contact-based foot locking off")
    p.add_argument("--no-hand-ik", action="store_true",
                   help="leave the leader's head and wrists where the network puts them (no IK onto the input)")
    p.add_argument("--leader-rig", default=None, metavar="FILE",
                   help="also retarget the leader onto the armature of this .blend, .glb/.gltf or .fbx file "
                        "(formats blend and fbx, --render; a file without an armature fails each take)")
    p.add_argument("--follower-rig", default=None, metavar="FILE",
                   help="the same for the follower")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (result lines only)")


def run(args, worker_cmd=None, out=None, err=None, in_blender=False) -> int:
    """The batch conversion for parsed :func:`add_arguments` options; returns the
    exit status (0 all done, 1 a file failed, 2 bad options or a cluster worker that
    refused, 130/143 stopped).
    Raises a :class:`UserError` (one line) for a bad command line, before any
    work: no inputs, missing or damaged models (:func:`~..nets.check_models`), an
    output or report that is an input, a report path that is not a report,
    another batch writing into the same output folder (:mod:`.lock`).
    ``worker_cmd``: how to start a worker (default: :func:`.worker.worker_command`)."""
    from ..nets import check_models

    out = out if out is not None else sys.stdout
    err = err if err is not None else sys.stderr
    t_start = time.perf_counter()
    started = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    fmt = args.format
    jobs = args.jobs or default_jobs()
    out_dir = os.path.abspath(os.path.expanduser(args.output_dir))
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise InputError(args.output_dir, "output path exists and is not a folder")
    needs_bpy = fmt in BPY_FORMATS or args.render
    cluster_addr = getattr(args, "cluster", None)
    entries = discover(args.inputs, BPY_INPUTS, exclude=[out_dir])
    if not entries:
        raise InputError(" ".join(map(str, args.inputs)), f"no input files found (looked for {', '.join(BPY_INPUTS)})")
    fbx = next((p for p, _ in entries if input_needs_bpy(p)), None)
    if needs_bpy and not in_blender and not cluster_addr:  # (on a cluster: the workers need bpy, checked there)
        import importlib.util
        if importlib.util.find_spec("bpy") is None:  # (only looks: the parent never imports it)
            raise InputError(None, f"--format {fmt}{' --render' if args.render else ''} needs Blender: "
                                   f"install the bpy module or run blender --background --command "
                                   f"dancing_points convert ...")
    if fbx is not None and not needs_bpy and not in_blender and not cluster_addr:
        import importlib.util
        if importlib.util.find_spec("bpy") is None:
            raise InputError(fbx, "FBX takes are read by Blender's importer: install the bpy module, or run "
                                  "blender --background --command dancing_points convert ...")
    model_dir = resolve_model_dir(args.models)
    if args.asf and not os.path.isfile(args.asf):
        raise InputError(args.asf, "no such ASF file")
    check_rigs(args, needs_bpy)
    if getattr(args, "audio", None):  # every take's song: read once, here, before any work
        from ..audio import read_song
        read_song(args.audio)
    if args.asf and needs_bpy:
        raise InputError(args.asf, "--asf works with the npz and bvh formats only (without --render); "
                                   "put the ASF beside the AMC files instead")
    report_path = os.path.abspath(os.path.expanduser(args.report)) if args.report else os.path.join(out_dir,
                                                                                                   REPORT_NAME)
    outputs = [o for outs in output_paths(entries, out_dir, fmt, args.render) for o in outs]
    check_not_inputs(entries, outputs)
    check_not_inputs(entries, [report_path], "report")
    if report_path in outputs:
        raise InputError(report_path, "--report: this path is one of the outputs; choose another path")
    check_report_path(report_path, args.overwrite, explicit=bool(args.report))
    check_models(model_dir, args.threads or 1)  # once, here: not every file against a damaged network
    cluster = None
    if cluster_addr:  # before any work: a cluster that cannot run this batch is one line, exit 2
        from .cluster_connect import connect

        cluster = connect(cluster_addr, model_dir, needs_bpy or fbx is not None, err=err)
    try:
        batch, outcome, report, report_path, seconds = _run_planned(
            args, entries, out_dir, fmt, jobs, model_dir, report_path, worker_cmd, cluster, out, err, t_start,
            started)
    finally:
        if cluster is not None:
            cluster.close()
    print(printable(summary_line(report, outcome, seconds, report_path)), file=out, flush=True)
    if batch.fatal:
        print(printable(f"error: {batch.fatal}"), file=err)
    if outcome == "refused":  # a worker of the cluster runs another version or models
        return EXIT_BAD_INPUT
    if outcome != "done":
        print(f"error: {outcome}; no partial outputs were left; re-run with --resume to convert the rest",
              file=err)
        return EXIT_TERMINATED if outcome == "terminated" else EXIT_INTERRUPTED
    # a report that could not be written (checked before the work; the disk may fill since) fails the run
    return EXIT_FAILURE if report["counts"]["failed"] or report_path is None else EXIT_OK


def _run_planned(args, entries, out_dir, fmt, jobs, model_dir, report_path, worker_cmd, cluster, out, err,
                 t_start, started):
    """The checked batch: lock the output folder, plan, run (locally or on ``cluster``),
    write the report; ``(batch, outcome, report, report_path or None, seconds)``."""
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise InputError(args.output_dir, f"cannot create the output folder ({exc.strerror or exc})") from None
    with acquire_lock(out_dir):  # one batch per output folder
        tasks = plan(entries, out_dir, fmt, args.render, args.overwrite, args.resume)
        remove_stale_temps(tasks)  # what a batch killed on the spot left beside these outputs
        made = make_output_dirs(tasks)  # sub-folders made for the outputs: removed again if they stay empty
        n_run = sum(t.status == "pending" for t in tasks)
        n_workers = min(jobs, max(n_run, 1))  # never more workers than files
        cores = default_jobs()
        if n_workers > cores and cluster is None:
            print(f"warning: --jobs {jobs}: {n_workers} worker processes on {cores} core{'s' if cores != 1 else ''} "
                  f"share them (each file takes longer, and each worker loads the networks)", file=err,
                  flush=True)
        prog = Progress(n_run, stream=err, out=out, enabled=not args.no_progress)
        for t in tasks:  # decided before any work: report now
            if t.status != "pending":
                prog.result(result_line(t, out_dir))
        if cluster is None:
            batch = Batch(tasks, n_workers, job_options(args, model_dir), fmt, worker_cmd, prog, out_dir)
        else:
            from .cluster import ClusterBatch

            batch = ClusterBatch(tasks, cluster, job_options(args, model_dir), fmt, prog, out_dir, jobs=args.jobs)
        outcome = batch.run()
        remove_empty_dirs(made)
        seconds = time.perf_counter() - t_start
        report = build_report(tasks, fmt, out_dir, batch.jobs, model_dir, started, seconds, outcome, batch.fatal)
        if cluster is not None:
            batch.annotate(report)
        try:
            write_report(report_path, report)
        except InputError as exc:
            print(printable(f"error: cannot write the report: {one_line(exc)}"), file=err)
            report_path = None
    return batch, outcome, report, report_path, seconds
