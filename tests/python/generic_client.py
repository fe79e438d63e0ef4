"""A generic gRPC client for Tessera (not the project's Rust code): submits a
scene and watches the job to completion. Stubs come from proto/ via
grpc_tools.protoc. Usage: generic_client.py HOST:PORT SCENE.toml"""
import sys

import grpc
from tessera.v1 import common_pb2, jobs_pb2, jobs_pb2_grpc

addr, scene_path = sys.argv[1], sys.argv[2]
with open(scene_path, "rb") as f:
    scene = f.read()

with grpc.insecure_channel(addr) as channel:
    jobs = jobs_pb2_grpc.JobServiceStub(channel)
    spec = jobs_pb2.JobSpec(
        name="from-python",
        scene_name=scene_path,
        scene=scene,
        overrides=common_pb2.RenderOverrides(width=64, height=48, samples=1),
    )
    meta = [("tessera-protocol-version", "1")]
    job_id = jobs.SubmitJob(jobs_pb2.SubmitJobRequest(spec=spec), metadata=meta).job_id
    print("job", job_id, flush=True)
    last = None
    for event in jobs.WatchJob(jobs_pb2.WatchJobRequest(job_id=job_id), metadata=meta):
        last = event
        pct = 100.0 * event.samples_done / max(event.samples_total, 1)
        print("progress", jobs_pb2.JobState.Name(event.state), f"{pct:.1f}", flush=True)
    pct = 100.0 * last.samples_done / max(last.samples_total, 1)
    print("final", jobs_pb2.JobState.Name(last.state), f"{pct:.1f}", flush=True)
    sys.exit(0 if last.state == jobs_pb2.JOB_STATE_DONE else 1)
