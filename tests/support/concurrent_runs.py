"""Independent short-lived command runs started together: their interpreters start up (imports, most of
a short run's wall time) side by side on the machine's cores instead of one after the other."""
from __future__ import annotations

import subprocess


def run_together(commands: list[list[str]], timeout: float = 60.0, envs: list[dict] | None = None,
                 **popen) -> list[subprocess.CompletedProcess]:
    """``[subprocess.run(c, capture_output=True, text=True, timeout=timeout, env=e, **popen) for c, e in
    zip(commands, envs)]``, the processes running at the same time; a command that outlives ``timeout`` is
    killed and raises."""
    envs = envs or [None] * len(commands)
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=e, **popen)
             for c, e in zip(commands, envs)]
    try:
        results = []
        for c, p in zip(commands, procs):
            out, err = p.communicate(timeout=timeout)
            results.append(subprocess.CompletedProcess(c, p.returncode, out, err))
        return results
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
