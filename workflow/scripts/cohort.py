"""The cohort rule's command: ``dicer cohort`` on the patients' reports and the benchmark
files of their stages, the paths given through an argument file beside the log (a cohort's
hundreds of paths would pass the 128 KB a shell command may have). No algorithm here."""

import subprocess
from pathlib import Path

smk = snakemake  # noqa: F821 -- given by Snakemake's script directive
log = Path(smk.log[0])
arguments = log.with_suffix(".args")
arguments.parent.mkdir(parents=True, exist_ok=True)
benchmarks = [b for b in smk.params.benchmarks if Path(b).is_file()]  # a deleted one leaves its cells empty
arguments.write_text("".join(f"{a}\n" for a in [*smk.input.reports, *(["--benchmarks", *benchmarks] if benchmarks
                                                                      else [])]), encoding="utf-8")
with open(log, "w", encoding="utf-8") as out:
    done = subprocess.run(["dicer", "cohort", f"@{arguments}", "-o", smk.output.html, "--tsv", smk.output.tsv],
                          stdout=out, stderr=subprocess.STDOUT)
raise SystemExit(done.returncode)
