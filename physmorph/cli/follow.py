"""Running the workflow for one experiment as a Snakemake process and following it: each job as it
starts, the morph's frames (k/K, the share of the gap closed, the time left) as they are done.

Snakemake's own output goes to results/{profile}/logs/physmorph/{experiment}.snakemake.log; the
frames are read from the morph job's log, which the morph writes a line per frame.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

# the venv's snakemake, beside this interpreter (as the Makefile's targets call it)
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
FRAME_LINE = re.compile(r"frame (\d+)/(\d+).*?\(gap closed (-?\d+) %\).*?ETA (\d+) s")
JOB_LINE = re.compile(r"^(?:local)?rule (\w+):\s*$")
WILDCARDS_LINE = re.compile(r"^\s+wildcards: (.*)$")
DONE_LINE = re.compile(r"^(\d+) of (\d+) steps \((\d+%)\) done")


@dataclass
class WorkflowCall:
    """``snakemake --cores N TARGETS --configfile FILES`` in ``workdir`` (the checkout's root)."""

    workdir: Path
    targets: list[str]
    configfiles: list[str]  # the profile's file (none for the default) and the morph's own
    cores: int = 2
    config: tuple[str, ...] = ()  # --config KEY=VALUE items
    extra: tuple[str, ...] = ()  # further snakemake arguments, as given

    def command(self, dry_run: bool = False) -> list[str]:
        # the targets come first: --configfile and --config take several values
        cmd = [str(SNAKEMAKE), "--cores", str(self.cores), *self.targets, *(["-n"] if dry_run else []),
               "--configfile", *self.configfiles]
        if self.config:
            cmd += ["--config", *self.config]
        return cmd + list(self.extra)


class _Tail:
    """New complete lines of a file that another process appends to (restarted if it is rewritten)."""

    def __init__(self, path: Path):
        self.path, self.offset, self.rest = path, 0, ""

    def lines(self) -> list[str]:
        try:
            size = self.path.stat().st_size
        except OSError:
            return []
        if size < self.offset:  # the job began its log anew
            self.offset, self.rest = 0, ""
        with open(self.path, "rb") as f:
            f.seek(self.offset)
            chunk = f.read().decode("utf-8", "replace")
        self.offset += len(chunk.encode("utf-8"))
        text = self.rest + chunk
        *complete, self.rest = text.split("\n")
        return complete


def frame_progress(line: str) -> str | None:
    """A morph log's frame line as `frame k/K: gap closed g %, ETA t s` (None for other lines)."""
    m = FRAME_LINE.search(line)
    return None if m is None else f"frame {m[1]}/{m[2]}: gap closed {m[3]} %, ETA {m[4]} s"


def follow(call: WorkflowCall, snakemake_log: Path, morph_log: Path, out: TextIO = sys.stdout,
           poll_s: float = 0.5) -> int:
    """Run ``call`` to its end, printing each job's start and the morph's frames; its exit status.
    Snakemake's whole output is kept in ``snakemake_log``; on a failure its last lines are printed."""
    snakemake_log.parent.mkdir(parents=True, exist_ok=True)
    morph_tail = _Tail(morph_log)
    morph_tail.lines()  # what an earlier run left there is not news
    with open(snakemake_log, "w") as log:
        # unbuffered: each line reaches the log (and this loop) as it is written, the jobs' too
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        proc = subprocess.Popen(call.command(), cwd=call.workdir, stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            _watch(proc, _Tail(snakemake_log), morph_tail, _JobNews(out), out, poll_s)
        except KeyboardInterrupt:  # a terminal's Ctrl-C reaches Snakemake too; an interrupt sent here alone is passed on
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGINT)
                proc.wait()  # Snakemake stops its jobs; the morph keeps its committed frames
            print("stopped: run the same command again to resume (the morph goes on from its last committed frame)",
                  file=out, flush=True)
            return 130
    if proc.returncode != 0:
        tail = snakemake_log.read_text(errors="replace").splitlines()[-25:]
        print("\n".join(["the workflow stopped; its last lines (whole output: " + str(snakemake_log) + "):", *tail]),
              file=out, flush=True)
    return proc.returncode


def _watch(proc: subprocess.Popen, sm_tail: _Tail, morph_tail: _Tail, news: "_JobNews", out: TextIO,
           poll_s: float) -> None:
    """Until ``proc`` ends: Snakemake's news of its jobs and the morph's frames, as they come."""
    while True:
        finished = proc.poll() is not None
        for line in sm_tail.lines():
            news.read(line)
        for line in morph_tail.lines():
            shown = frame_progress(line) or (line.strip() if "resuming" in line or "warning" in line else None)
            if shown:
                print(f"  morph: {shown}", file=out, flush=True)
        if finished:
            return
        time.sleep(poll_s)


class _JobNews:
    """Snakemake's lines about a job (its rule, then its fields, resources last) as one line per job
    started, and the count of jobs done."""

    def __init__(self, out: TextIO):
        self.out, self.rule, self.wildcards = out, None, ""

    def read(self, line: str) -> None:
        if (m := JOB_LINE.match(line)) is not None:
            self.rule, self.wildcards = m[1], ""
        elif self.rule and (w := WILDCARDS_LINE.match(line)) is not None:
            self.wildcards = w[1]
        elif self.rule and line.strip().startswith("resources:"):
            self._say(f"job {self.rule}" + (f" ({self.wildcards})" if self.wildcards else ""))
            self.rule = None
        elif (d := DONE_LINE.match(line.strip())) is not None:
            self._say(f"  {d[1]} of {d[2]} jobs done")
        elif line.startswith("Nothing to be done"):
            self._say("nothing to be done: every output is there")

    def _say(self, text: str) -> None:
        print(text, file=self.out, flush=True)
