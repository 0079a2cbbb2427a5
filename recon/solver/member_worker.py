"""One ensemble member in its own process (started by :func:`recon.solver.members.fit_members`):

    python -m recon.solver.member_worker VARIANT DATASET.pkl JOB.pkl RESULT.pkl

fits :func:`recon.solver.loop.fit_member` with the pickled dataset and keywords (JOB.pkl: the
keywords and the output locks the parent holds for this worker), prints one
``member-report [iteration, record]`` line per iteration on stdout and pickles (volume, run)
— or the error — to RESULT.pkl (atomically: a file there is a whole outcome).
"""
from __future__ import annotations

import json
import pickle
import sys

from .members import REPORT


def main(argv: list[str]) -> int:
    variant, data_path, job_path, result_path = argv
    out = sys.stdout
    sys.stdout = sys.stderr          # stdout carries the reports only

    def report(iteration, record):
        out.write(REPORT + json.dumps([iteration, record], default=float) + "\n")
        out.flush()
    try:
        from sonarsim import runtime
        runtime.set_variant(variant)
        from .loop import fit_member
        with open(data_path, "rb") as f:
            dataset = pickle.load(f)
        with open(job_path, "rb") as f:
            job, locks = pickle.load(f)
        from sonarsim import outputs
        for path in locks:            # held by the parent for this worker
            outputs.inherit_lock(path)
        outcome = fit_member(dataset=dataset, **job, progress=False, callback=report)
        status = 0
    except KeyboardInterrupt:        # Ctrl-C reaches the whole process group: the parent reports it
        return 130
    except Exception as exc:         # handed to the parent, which raises it
        outcome, status = exc, 1
    try:
        payload = pickle.dumps(outcome, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:         # an error that cannot travel: its message does
        from sonarsim.errors import SonarsimError
        payload = pickle.dumps(SonarsimError(f"{type(outcome).__name__}: {outcome}"
                                             if status else f"result not picklable: {exc}"))
        status = 1
    from sonarsim.atomic import atomic_path
    with atomic_path(result_path) as tmp:
        tmp.write_bytes(payload)
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
