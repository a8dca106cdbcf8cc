"""``drago study --backend slurm``: the study's plan as SLURM batch jobs, submitted with submitit.

The plan is the local backend's (:func:`drago.study.plan.plan_study`): what each job does follows from its
directory. Here every job becomes a SLURM batch job, and the order is SLURM's to keep:

* a run's transfers wait for it (``--dependency=afterok:RUN``), the report job for every job of the study
  (``afterany``); a job whose run failed is cancelled by SLURM (``--kill-on-invalid-dep=yes``) instead of
  waiting forever;
* ``--jobs N`` caps the jobs running at once: the jobs are dealt into N lanes, one SLURM job name each, and
  ``--dependency=singleton`` lets one job of a name run at a time;
* the command returns once the jobs are submitted; the job ids are kept in ``OUT/slurm/jobs.json``.

Each job runs ``python -m drago ARGS`` (:class:`~drago.study.slurm.node.StudyJob`, pickled by submitit), with
``ARGS`` worked out on the node when the job starts: ``drago train``/``drago transfer`` in an empty directory,
``drago resume DIR`` in an interrupted one, nothing in a finished one. Its output is appended to ``OUT/logs/`` as
with the local backend. SLURM signals a job (USR2) shortly before its time limit; submitit then calls
:meth:`~drago.study.slurm.node.StudyJob.checkpoint`, which stops drago (SIGTERM, as Ctrl-C) and has the job
requeued under the same id; the requeued job resumes from the run's last checkpoint. A preempted or cancelled
job, or one whose node failed, is continued the same way by running the study command again.

Job states come from ``squeue -t all`` and from the run directories, never from ``sacct``: without the
accounting daemon (slurmdbd) there is no ``sacct``, and submitit reports every state as UNKNOWN. ``squeue``
lists finished jobs for ``MinJobAge`` seconds (300 by default); after that the run directories, which say
exactly what is finished, are the only record needed.

The modules: :mod:`~drago.study.slurm.options` checks what every job asks for (``--partition``, ``--time``,
``--sbatch``, ...); :mod:`~drago.study.slurm.submission` turns the plan into SLURM jobs and submits them;
:mod:`~drago.study.slurm.monitoring` asks SLURM about them (``--status``, ``--wait``); and
:mod:`~drago.study.slurm.node` is what a job runs on its node.
"""
