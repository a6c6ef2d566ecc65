"""What a SLURM cluster offers, and whether a job can ever run on it.

The workflow (workflow/rules/common.smk) asks this module, when it runs with the SLURM executor,
to cap each rule's threads at the CPUs of the partition's largest node and, before any job is
submitted, to check every job's CPUs, memory, GPUs and time limit against its partition. A job
that no node can hold would otherwise stay pending for ever (SLURM's reason ``PartitionConfig``,
``PartitionTimeLimit``, ``Resources``) with no word from Snakemake; here it stops the run with an
error that names the setting to change. Also checked: job accounting, without which the executor
cannot see a job end.

Reads the cluster with ``sinfo``, ``scontrol`` and ``sacctmgr``; the parsing is separate
(``parse_*``) and testable without a cluster. Does not import snakemake.
"""

from __future__ import annotations

import getpass
import os
import re
import shutil
import subprocess
from dataclasses import dataclass, field


class ClusterError(RuntimeError):
    """A job that the cluster can never run, or a cluster the workflow cannot drive."""


@dataclass(frozen=True)
class Node:
    cpus: int
    mem_mb: int
    gpus: int


@dataclass(frozen=True)
class Partition:
    name: str
    nodes: tuple[Node, ...]
    max_minutes: int | None = None  # MaxTime; None: no limit
    max_cpus_per_node: int | None = None  # MaxCPUsPerNode; None: no limit
    max_mem_per_node: int | None = None  # MaxMemPerNode (MB); None: no limit
    default: bool = False

    def usable(self, node: Node) -> Node:
        """A node as this partition lets one job use it."""
        cpus = node.cpus if self.max_cpus_per_node is None else min(node.cpus, self.max_cpus_per_node)
        mem = node.mem_mb if self.max_mem_per_node is None else min(node.mem_mb, self.max_mem_per_node)
        return Node(cpus, mem, node.gpus)

    @property
    def max_cpus(self) -> int:
        return max((self.usable(n).cpus for n in self.nodes), default=0)

    @property
    def max_mem_mb(self) -> int:
        return max((self.usable(n).mem_mb for n in self.nodes), default=0)

    @property
    def max_gpus(self) -> int:
        return max((n.gpus for n in self.nodes), default=0)


@dataclass(frozen=True)
class Cluster:
    partitions: dict[str, Partition]
    accounting: str = "accounting_storage/slurmdbd"  # AccountingStorageType
    min_job_age_s: int | None = None
    user_accounts: tuple[str, ...] = field(default_factory=tuple)

    def partition(self, name: str | None) -> Partition:
        if name:
            if name not in self.partitions:
                raise ClusterError(f"partition '{name}' does not exist on this cluster "
                                   f"(partitions: {', '.join(sorted(self.partitions)) or 'none'})")
            return self.partitions[name]
        default = [p for p in self.partitions.values() if p.default]
        if not default:
            raise ClusterError("this cluster has no default partition: name one with "
                               "--default-resources slurm_partition=NAME "
                               f"(partitions: {', '.join(sorted(self.partitions)) or 'none'})")
        return default[0]


# ----------------------------------------------------------------------------------- parsing

def parse_minutes(text: str) -> int | None:
    """A SLURM time limit ('infinite', 'MM', 'MM:SS', 'HH:MM:SS', 'D-HH', 'D-HH:MM', 'D-HH:MM:SS')
    in whole minutes (seconds round up); None for no limit."""
    t = text.strip()
    if t.lower() in ("infinite", "unlimited", "n/a", "none", ""):
        return None
    days, _, rest = t.rpartition("-")
    parts = [int(p) for p in rest.split(":")]
    if days:
        h, m, s = (parts + [0, 0])[:3]
    else:
        h, m, s = {1: (0, parts[0], 0), 2: (0, *parts), 3: tuple(parts)}[len(parts)]
    return int(days or 0) * 1440 + h * 60 + m + (1 if s > 0 else 0)


def parse_gpus(gres: str) -> int:
    """GPUs in a node's GRES string ('gpu:4', 'gpu:a100:2(S:0-1)', 'gpu:1,shard:8', 'gpu', '(null)')."""
    total = 0
    for item in re.sub(r"\(.*?\)", "", gres or "").split(","):
        fields = item.strip().split(":")
        if fields[0] == "gpu":
            total += int(fields[-1]) if len(fields) > 1 and fields[-1].isdigit() else 1
    return total


def parse_sinfo_nodes(text: str) -> dict[str, tuple[bool, list[Node]]]:
    """``sinfo -h -N -o '%P|%c|%m|%G'`` -> partition -> (is default, its nodes)."""
    out: dict[str, tuple[bool, list[Node]]] = {}
    for line in text.splitlines():
        if not line.strip():
            continue
        part, cpus, mem, gres = (line.split("|") + ["", "", "", ""])[:4]
        default = part.endswith("*")
        part = part.rstrip("*")
        mem_mb = int(re.match(r"\d+", mem).group()) if re.match(r"\d+", mem.strip()) else 0
        cpu_n = int(re.match(r"\d+", cpus.strip()).group()) if re.match(r"\d+", cpus.strip()) else 0
        is_default, nodes = out.get(part, (False, []))
        nodes.append(Node(cpu_n, mem_mb, parse_gpus(gres)))
        out[part] = (is_default or default, nodes)
    return out


def parse_key_values(line: str) -> dict[str, str]:
    """``scontrol show ... -o`` style 'Key=Value Key=Value' into a dict."""
    return dict(m.groups() for m in re.finditer(r"(\w+)=(\S*)", line))


def parse_partitions(sinfo: str, scontrol_partitions: str) -> dict[str, Partition]:
    """Partitions from ``sinfo -h -N -o '%P|%c|%m|%G'`` and ``scontrol -o show partition``."""
    limits = {}
    for line in scontrol_partitions.splitlines():
        kv = parse_key_values(line)
        if "PartitionName" in kv:
            limits[kv["PartitionName"]] = kv

    def number(v: str | None) -> int | None:
        return int(v) if v and v.isdigit() and int(v) > 0 else None

    parts = {}
    for name, (default, nodes) in parse_sinfo_nodes(sinfo).items():
        kv = limits.get(name, {})
        parts[name] = Partition(
            name=name, nodes=tuple(nodes), default=default or kv.get("Default") == "YES",
            max_minutes=parse_minutes(kv["MaxTime"]) if "MaxTime" in kv else None,
            max_cpus_per_node=number(kv.get("MaxCPUsPerNode")),
            max_mem_per_node=number(kv.get("MaxMemPerNode")))
    return parts


def parse_config(text: str) -> dict[str, str]:
    """``scontrol show config`` -> key -> value."""
    out = {}
    for line in text.splitlines():
        if "=" in line:
            k, v = line.split("=", 1)
            out[k.strip()] = v.strip()
    return out


# ----------------------------------------------------------------------------------- reading

def _run(cmd: list[str]) -> str:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=60).stdout
    except FileNotFoundError as exc:
        raise ClusterError(f"'{cmd[0]}' is not installed here: the SLURM executor needs the SLURM client tools "
                           "on the machine that runs snakemake") from exc
    except subprocess.CalledProcessError as exc:
        raise ClusterError(f"'{' '.join(cmd)}' failed: {exc.stderr.strip() or exc.stdout.strip()}") from exc
    except subprocess.TimeoutExpired as exc:
        raise ClusterError(f"'{' '.join(cmd)}' did not answer within 60 s") from exc


def read_cluster() -> Cluster:
    """This machine's SLURM cluster, read with sinfo, scontrol (and sacctmgr for the accounts)."""
    partitions = parse_partitions(_run(["sinfo", "-h", "-N", "-o", "%P|%c|%m|%G"]),
                                  _run(["scontrol", "-o", "show", "partition"]))
    if not partitions:
        raise ClusterError("sinfo lists no partition: is slurmctld up (scontrol ping)?")
    config = parse_config(_run(["scontrol", "show", "config"]))
    age = re.match(r"\d+", config.get("MinJobAge", ""))
    accounts: tuple[str, ...] = ()
    if shutil.which("sacctmgr") and "none" not in config.get("AccountingStorageType", ""):
        try:
            text = _run(["sacctmgr", "-n", "-P", "show", "assoc", f"user={getpass.getuser()}", "format=account"])
            accounts = tuple(sorted({a.strip() for a in text.splitlines() if a.strip()}))
        except ClusterError:
            pass
    return Cluster(partitions=partitions, accounting=config.get("AccountingStorageType", ""),
                   min_job_age_s=int(age.group()) if age else None, user_accounts=accounts)


# ---------------------------------------------------------------------------------- checking

def cap_threads(threads: int, partition: Partition) -> int:
    """A rule's threads, at most the CPUs one job can have on the partition's largest node."""
    return max(1, min(int(threads), partition.max_cpus)) if partition.max_cpus else int(threads)


@dataclass(frozen=True)
class JobRequest:
    """One job as it would be submitted, with where each number came from (for the error)."""

    label: str  # e.g. "morph (iso_bunny_full)"
    rule: str
    threads: int
    mem_mb: int | None
    gpus: int
    runtime_min: int | None
    partition: str | None
    threads_from: str  # the setting behind each number, named in the error
    mem_from: str
    gpus_from: str
    runtime_from: str


def check_job(job: JobRequest, cluster: Cluster) -> list[str]:
    """Why this job could never start on its partition ([] when some node can run it)."""
    try:
        part = cluster.partition(job.partition)
    except ClusterError as exc:
        return [f"{job.label}: {exc}"]
    problems = []
    where = f"partition '{part.name}'"
    if job.threads > part.max_cpus:
        problems.append(f"{job.label} asks {job.threads} CPUs (from {job.threads_from}), but the largest node of {where} "
                        f"offers {part.max_cpus}: lower {job.threads_from}")
    if job.mem_mb is not None and job.mem_mb > part.max_mem_mb:
        problems.append(f"{job.label} asks mem_mb={job.mem_mb} (from {job.mem_from}), but the largest node of {where} has "
                        f"{part.max_mem_mb} MB: pick a partition with bigger nodes (--set-resources {job.rule}:slurm_partition=NAME) "
                        f"or lower {job.mem_from}")
    if job.gpus > part.max_gpus:
        have = f"at most {part.max_gpus} GPUs per node" if part.max_gpus else "no node with a GPU (GRES gpu)"
        problems.append(f"{job.label} asks {job.gpus} GPU(s) (from {job.gpus_from}), but {where} has {have}: "
                        f"pick a GPU partition (--set-resources {job.rule}:slurm_partition=NAME) or set {job.gpus_from} lower")
    if not problems and not any(n.cpus >= job.threads and (job.mem_mb or 0) <= n.mem_mb and n.gpus >= job.gpus
                                for n in map(part.usable, part.nodes)):
        problems.append(f"{job.label} asks {job.threads} CPUs, mem_mb={job.mem_mb} and {job.gpus} GPU(s) together, "
                        f"but no single node of {where} has them all: lower {job.threads_from} or {job.mem_from}")
    if job.runtime_min is not None and part.max_minutes is not None and job.runtime_min > part.max_minutes:
        problems.append(f"{job.label} asks runtime={job.runtime_min} min (from {job.runtime_from}), but {where} allows "
                        f"{part.max_minutes} min: set --set-resources {job.rule}:runtime={part.max_minutes} (a morph killed at "
                        "its time limit resumes from its last checkpoint on the next attempt: raise --retries "
                        "to give it enough attempts) or pick a partition with a longer limit")
    return problems


# the executor waits up to this long between two looks at the jobs' states
STATUS_CHECK_MAX_S = 180


def check_status(cluster: Cluster, status_command: str | None) -> str | None:
    """Why the executor could not see every job end (None when it can).

    With ``squeue`` (the profile's choice) a job is seen for MinJobAge seconds after it ends, which
    must outlast the executor's longest wait between two looks. With ``sacct`` job accounting must
    be on; and the executor does not recognise sacct's state of a cancelled job ('CANCELLED by
    <uid>'), so a job cancelled with scancel (by a user or an admin) is never seen to end."""
    accounting = "none" not in cluster.accounting
    age = cluster.min_job_age_s
    if status_command == "squeue":
        if age is not None and age > STATUS_CHECK_MAX_S:
            return None
        return (f"SLURM keeps a finished job in squeue for MinJobAge={age} s, shorter than the executor's longest wait "
                f"between two looks at the jobs ({STATUS_CHECK_MAX_S} s): a job that ends may vanish unseen and the run "
                "wait for ever. Ask the site for MinJobAge >= 300 (SLURM's default)"
                + (", or run with --slurm-status-command sacct (job accounting is on here; a job cancelled with "
                   "scancel is then not seen to end)" if accounting else ""))
    if not accounting:
        return (f"SLURM job accounting is off here (AccountingStorageType={cluster.accounting}) and the executor "
                "reads job states with sacct: it would wait for ever after the jobs finish. Run with "
                "--slurm-status-command squeue (workflow/profiles/slurm does) or turn accounting on (slurmdbd)")
    return None


def check_account(cluster: Cluster, account: str | None) -> str | None:
    """A note when no account is given (the executor then guesses, printing 'sacct: invalid option')."""
    if account:
        return None
    yours = f" (yours: {', '.join(cluster.user_accounts)})" if cluster.user_accounts else ""
    return ("no SLURM account given: pass --default-resources slurm_account=NAME" + yours +
            "; without one the executor guesses it (printing 'sacct: invalid option') and submits with your default account")


def job_threads_here(threads: int) -> int:
    """Inside a job: the rule's threads, at most the CPUs this process may use (SLURM's allocation)."""
    try:
        return max(1, min(int(threads), len(os.sched_getaffinity(0))))
    except (AttributeError, OSError):
        return int(threads)
