"""The S3 keys each pod of deploy/ holds, and the MinIO policies behind them, without a cluster.

A RayService behind an Ingress holds only the reader's keys, whose policy lets it list and read
the served bucket and nothing else; the RayJobs' Ray pods hold the writer's, whose policy
writes, and their submitters none; the bucket Job of deploy/minio/minio.yaml gives each key
pair its policy. (A private RayService may hold the writer's: deploy/RUNBOOK.md, section 6.)

Each check returns the problems it finds, and `test_a_planted_mistake_is_found` shows each one
finding a mistake planted in a copy (tests/support/manifests.py holds the parsed manifests and
the helpers the test_deploy_*.py files share).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from typing import Any

import pytest

from tests.support.manifests import (
    MANIFESTS,
    PUBLIC,
    Check,
    Manifests,
    Plant,
    edit,
    exposed_services,
    objects,
    planted_copy,
    pod_templates,
    serve_configs,
    the_app,
)

#: The Secrets of S3 keys: the writer's (generation, curation, the index) and the reader's
#: (the pods of a public RayService).
WRITER_SECRET, READER_SECRET = "links-s3-credentials", "links-s3-reader"
#: The MinIO policy files in the ConfigMap of deploy/minio/minio.yaml.
WRITER_POLICY, READER_POLICY = "links-readwrite", "links-readonly"
#: All a reader may do: list the bucket and get its objects.
READ_ACTIONS = {"s3:GetObject", "s3:ListBucket", "s3:GetBucketLocation"}


def secrets_named(value: Any) -> set[str]:
    """Names of the Secrets a pod spec (or any part of one) reads: keys of env, envFrom and
    volumes."""
    found: set[str] = set()
    if isinstance(value, dict):
        for key, inner in value.items():
            if key in ("secretKeyRef", "secretRef") and isinstance(inner, dict):
                found.add(inner.get("name"))
            elif key == "secret" and isinstance(inner, dict):
                found.add(inner.get("secretName"))
            else:
                found |= secrets_named(inner)
    elif isinstance(value, list):
        for inner in value:
            found |= secrets_named(inner)
    return found


def policies(manifests: Manifests) -> dict[str, dict]:
    """The MinIO policies of the ConfigMap that holds them, by name."""
    found = {}
    for _, config_map in objects(manifests, "ConfigMap"):
        for name, text in config_map.get("data", {}).items():
            if name.endswith(".json") and name.removesuffix(".json") in (
                WRITER_POLICY,
                READER_POLICY,
            ):
                found[name.removesuffix(".json")] = json.loads(text)
    return found


def allowed(policy: dict) -> dict[str, set[str]]:
    """Action to the resources an IAM policy allows it on."""
    granted: dict[str, set[str]] = {}
    for statement in policy["Statement"]:
        actions = statement["Action"]
        resources = statement["Resource"]
        for action in [actions] if isinstance(actions, str) else actions:
            granted.setdefault(action, set()).update(
                [resources] if isinstance(resources, str) else resources
            )
    return granted


# -- the checks -----------------------------------------------------------------------------


def key_problems(manifests: Manifests) -> list[str]:
    """A RayService behind an Ingress holds only the reader's keys, whose policy lets it list
    and read the served bucket and nothing else; the RayJobs' Ray pods hold the writer's,
    whose policy writes, and their submitters none; the bucket Job gives each key pair its
    policy."""
    problems = []
    exposed = exposed_services(manifests)
    for where, service in objects(manifests, "RayService"):
        if service["metadata"]["name"] not in exposed:
            continue  # private: it may build and save its own index (RUNBOOK.md, section 6)
        for group, template in pod_templates(service["spec"]["rayClusterConfig"]):
            held = secrets_named(template["spec"])
            if held != {READER_SECRET}:
                problems.append(
                    f"{where}: public {group} pods hold {sorted(held)}, not only {READER_SECRET}"
                )
    templates = {secret["metadata"]["name"] for _, secret in objects(manifests, "Secret")}
    for name in sorted({WRITER_SECRET, READER_SECRET} - templates):
        problems.append(f"no template of the Secret {name} under deploy/")
    for where, job in objects(manifests, "RayJob"):
        for group, template in pod_templates(job["spec"]["rayClusterSpec"]):
            held = secrets_named(template["spec"])
            if held != {WRITER_SECRET}:
                problems.append(f"{where}: {group} pods hold {sorted(held)}, not {WRITER_SECRET}")
        submitter = job["spec"].get("submitterPodTemplate", {})
        if secrets_named(submitter):
            problems.append(f"{where}: the submitter holds {sorted(secrets_named(submitter))}")
    found = policies(manifests)
    if set(found) != {WRITER_POLICY, READER_POLICY}:
        return [*problems, f"policies {sorted(found)}, not {WRITER_POLICY} and {READER_POLICY}"]
    buckets = {
        root.removeprefix("s3://").split("/")[0]
        for _, config in serve_configs(manifests)
        if (root := str(the_app(config).get("args", {}).get("root", ""))).startswith("s3://")
    }
    arns = {f"arn:aws:s3:::{bucket}" for bucket in buckets}
    arns |= {f"{arn}/*" for arn in arns}
    reader, writer = allowed(found[READER_POLICY]), allowed(found[WRITER_POLICY])
    if any(s["Effect"] != "Allow" for s in found[READER_POLICY]["Statement"]):
        problems.append(f"{READER_POLICY}: only Allow statements can be checked here")
    for action, resources in reader.items():
        if action not in READ_ACTIONS:
            problems.append(f"{READER_POLICY} allows {action}: it may only list and read")
        if not resources <= arns:
            problems.append(f"{READER_POLICY} allows {action} on {sorted(resources - arns)}")
    for action in ("s3:GetObject", "s3:ListBucket"):
        if action not in reader:
            problems.append(f"{READER_POLICY} lacks {action}, which serving needs")
    for action in ("s3:GetObject", "s3:ListBucket", "s3:PutObject", "s3:DeleteObject"):
        if action not in writer:
            problems.append(f"{WRITER_POLICY} lacks {action}, which the jobs need")
    problems += bucket_job_problems(manifests)
    return problems


def bucket_job_problems(manifests: Manifests) -> list[str]:
    """The bucket Job attaches the writer's policy to the writer's keys and the reader's to
    the reader's (the env var its script names, read from which Secret)."""
    problems = []
    for where, job in objects(manifests, "Job"):
        (container,) = job["spec"]["template"]["spec"]["containers"]
        script = "\n".join(container.get("args", []))
        if "mc admin policy" not in script:
            continue
        secret_of = {
            item["name"]: item["valueFrom"]["secretKeyRef"]["name"]
            for item in container.get("env", [])
            if "secretKeyRef" in item.get("valueFrom", {})
        }
        attached = {
            secret_of.get(variable): policy
            for variable, policy in re.findall(
                r'user_with_policy "\$(\w+)" "\$\w+" (links-[\w-]+)', script
            )
        }
        wanted = {WRITER_SECRET: WRITER_POLICY, READER_SECRET: READER_POLICY}
        if attached != wanted:
            problems.append(f"{where}: attaches {attached}, not {wanted}")
    return problems


# -- the tests ------------------------------------------------------------------------------


def test_public_pods_hold_read_only_keys_and_jobs_the_writers() -> None:
    assert exposed_services(MANIFESTS)  # a RayService behind an Ingress, checked
    assert key_problems(MANIFESTS) == []


# -- each check finds a planted mistake -----------------------------------------------------


MINIO = "minio/minio.yaml"


def worker_env(secret: str) -> Callable[[dict], None]:
    def change(service: dict) -> None:
        group = service["spec"]["rayClusterConfig"]["workerGroupSpecs"][0]
        (container,) = group["template"]["spec"]["containers"]
        container["env"][-1]["valueFrom"]["secretKeyRef"]["name"] = secret

    return change


def reader_policy_allows(action: str) -> Callable[[dict], None]:
    def change(config_map: dict) -> None:
        policy = json.loads(config_map["data"][f"{READER_POLICY}.json"])
        policy["Statement"][-1]["Action"].append(action)
        config_map["data"][f"{READER_POLICY}.json"] = json.dumps(policy)

    return change


def in_script(old: str, new: str) -> Callable[[dict], None]:
    def change(job: dict) -> None:
        (container,) = job["spec"]["template"]["spec"]["containers"]
        assert old in container["args"][0]
        container["args"][0] = container["args"][0].replace(old, new)

    return change


#: (check, the mistake planted, a phrase of the problem it must report).
PLANTED: list[tuple[Check, Plant, str]] = [
    (
        key_problems,
        lambda m: edit(m, PUBLIC, "links-public", worker_env(WRITER_SECRET)),
        "not only links-s3-reader",
    ),
    (
        key_problems,
        lambda m: edit(m, MINIO, "minio-policies", reader_policy_allows("s3:PutObject")),
        "allows s3:PutObject",
    ),
    (
        key_problems,
        lambda m: edit(m, MINIO, "minio-policies", reader_policy_allows("s3:*")),
        "allows s3:*",
    ),
    (
        key_problems,
        lambda m: edit(
            m,
            MINIO,
            "minio-create-bucket",
            in_script(
                '"$READER_SECRET_ACCESS_KEY" links-readonly',
                '"$READER_SECRET_ACCESS_KEY" links-readwrite',
            ),
        ),
        "attaches",
    ),
]


@pytest.mark.parametrize(
    ("check", "plant", "phrase"), PLANTED, ids=[phrase for _, _, phrase in PLANTED]
)
def test_a_planted_mistake_is_found(check: Check, plant: Plant, phrase: str) -> None:
    found = check(planted_copy(plant))
    assert any(phrase in problem for problem in found), found
