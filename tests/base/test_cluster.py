"""physmorph.base.cluster without a cluster: reading sinfo/scontrol output, capping threads, and the
check that stops a job no node can hold (naming the setting) before it is submitted. The same
checks on a running SLURM: tests/workflow/test_slurm.py (pytest -m slurm)."""

import pytest

from physmorph.base.cluster import (Cluster, ClusterError, JobRequest, Node, Partition, cap_threads, check_account, check_status,
                               check_job, parse_config, parse_gpus, parse_minutes,
                               parse_partitions)

SINFO = """debug*|2|21694|(null)
gpu|32|256000|gpu:a100:4(S:0-1)
gpu|16|128000|gpu:2
big|128|1024000|(null)
big|64|512000|(null)
"""
SCONTROL = """PartitionName=debug Default=YES MaxTime=UNLIMITED MaxCPUsPerNode=UNLIMITED MaxMemPerNode=UNLIMITED
PartitionName=gpu Default=NO MaxTime=2-00:00:00 MaxCPUsPerNode=UNLIMITED MaxMemPerNode=UNLIMITED
PartitionName=big Default=NO MaxTime=04:00:00 MaxCPUsPerNode=96 MaxMemPerNode=UNLIMITED
"""


@pytest.fixture
def cluster():
    return Cluster(partitions=parse_partitions(SINFO, SCONTROL), user_accounts=("physmorph",))


def _job(**kw):
    base = dict(label="morph (iso_bunny_full)", rule="morph", threads=2, mem_mb=600, gpus=0, runtime_min=10,
                partition=None, threads_from="the morph rule's threads", mem_from="its memory estimate",
                gpus_from="config key 'morph_gpus'", runtime_from="the morph rule's runtime estimate")
    return JobRequest(**{**base, **kw})


@pytest.mark.parametrize("text, minutes", [("infinite", None), ("UNLIMITED", None), ("30", 30), ("30:15", 31),
                                           ("04:00:00", 240), ("1-00:00:00", 1440), ("2-12", 3600), ("1-02:30", 1590)])
def test_time_limits_in_minutes(text, minutes):
    assert parse_minutes(text) == minutes


@pytest.mark.parametrize("gres, gpus", [("(null)", 0), ("gpu:4", 4), ("gpu:a100:2(S:0-1)", 2), ("gpu:1,shard:8", 1),
                                        ("gpu", 1), ("gpu:a100", 1), ("shard:8", 0)])
def test_gpus_from_gres(gres, gpus):
    assert parse_gpus(gres) == gpus


def test_partitions_hold_their_nodes_and_limits(cluster):
    debug, gpu, big = (cluster.partitions[n] for n in ("debug", "gpu", "big"))
    assert debug.default and not gpu.default and cluster.partition(None) is debug
    assert (debug.max_cpus, debug.max_mem_mb, debug.max_gpus, debug.max_minutes) == (2, 21694, 0, None)
    assert (gpu.max_cpus, gpu.max_gpus, gpu.max_minutes) == (32, 4, 2880)
    assert big.max_cpus == 96 and big.max_minutes == 240  # MaxCPUsPerNode caps the 128-CPU node
    with pytest.raises(ClusterError, match="partition 'nosuch' does not exist.*big, debug, gpu"):
        cluster.partition("nosuch")


def test_threads_are_capped_at_the_largest_node(cluster):
    assert cap_threads(8, cluster.partition("debug")) == 2
    assert cap_threads(8, cluster.partition("gpu")) == 8
    assert cap_threads(200, cluster.partition("big")) == 96


def test_a_job_that_fits_passes(cluster):
    assert check_job(_job(), cluster) == []
    assert check_job(_job(threads=32, gpus=4, mem_mb=200000, partition="gpu"), cluster) == []


def test_too_many_cpus_names_the_setting(cluster):
    (msg,) = check_job(_job(threads=8, threads_from="--set-threads morph=8"), cluster)
    assert "asks 8 CPUs (from --set-threads morph=8)" in msg and "partition 'debug' offers 2" in msg


def test_too_much_memory_names_the_setting(cluster):
    (msg,) = check_job(_job(mem_mb=50000, mem_from="--set-resources morph:mem_mb"), cluster)
    assert "mem_mb=50000 (from --set-resources morph:mem_mb)" in msg and "has 21694 MB" in msg


def test_a_gpu_job_on_a_partition_without_gpus_names_morph_gpus(cluster):
    (msg,) = check_job(_job(gpus=1), cluster)
    assert "config key 'morph_gpus'" in msg and "no node with a GPU" in msg
    assert check_job(_job(gpus=1, partition="gpu"), cluster) == []
    (msg,) = check_job(_job(gpus=8, partition="gpu"), cluster)
    assert "at most 4 GPUs per node" in msg


def test_resources_no_single_node_has_together(cluster):
    # 20 CPUs, 2 GPUs and 200 GB: only the 4-GPU node has them all, and that is enough
    assert check_job(_job(threads=20, gpus=2, mem_mb=200000, partition="gpu"), cluster) == []
    # 32 CPUs exist, and 32 GB, but not on one node
    split = Cluster(partitions={"p": Partition("p", (Node(64, 1000, 0), Node(8, 64000, 0)), default=True)})
    (msg,) = check_job(_job(threads=32, mem_mb=32000), split)
    assert "no single node of partition 'p' has them all" in msg


def test_a_run_time_above_the_partition_limit_names_the_setting(cluster):
    (msg,) = check_job(_job(runtime_min=610, partition="big"), cluster)
    assert "runtime=610 min (from the morph rule's runtime estimate)" in msg and "allows 240 min" in msg
    assert "--set-resources morph:runtime=240" in msg and "resumes from its last checkpoint" in msg


def test_unknown_partition_is_named(cluster):
    (msg,) = check_job(_job(partition="nosuch"), cluster)
    assert "partition 'nosuch' does not exist" in msg


def test_job_states_must_stay_visible_until_the_executor_looks():
    off = Cluster(partitions={}, accounting="accounting_storage/none", min_job_age_s=300)
    on = Cluster(partitions={}, accounting="accounting_storage/slurmdbd", min_job_age_s=300)
    short = Cluster(partitions={}, accounting="accounting_storage/slurmdbd", min_job_age_s=60)
    # squeue (the profile's choice) needs no accounting, only MinJobAge above the longest wait
    assert check_status(off, "squeue") is None and check_status(on, "squeue") is None
    msg = check_status(short, "squeue")
    assert "MinJobAge=60 s" in msg and "--slurm-status-command sacct" in msg
    # sacct needs accounting
    msg = check_status(off, "sacct")
    assert "AccountingStorageType=accounting_storage/none" in msg and "--slurm-status-command squeue" in msg
    assert check_status(on, "sacct") is None


def test_a_missing_account_is_a_note_naming_the_users_accounts(cluster):
    assert check_account(cluster, "physmorph") is None
    note = check_account(cluster, None)
    assert "--default-resources slurm_account=NAME (yours: physmorph)" in note


def test_scontrol_config_is_read():
    cfg = parse_config("AccountingStorageType   = accounting_storage/slurmdbd\nMinJobAge               = 300 sec\n")
    assert cfg == {"AccountingStorageType": "accounting_storage/slurmdbd", "MinJobAge": "300 sec"}
