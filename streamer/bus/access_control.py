"""The access-control list a run's routers apply: who may publish, answer and ask what.

Zenoh's ``access_control`` section, keyed by the certificate's common name (the identities
of :mod:`streamer.bus.security`, which says what each may do): every identity may subscribe
and query (read); a stage publishes its own topic, progress, liveliness token and errors,
and answers the commands sent to it, and may not ask another stage's commands (a query on a
command key is a command); the launcher and ``ttl control`` send commands, progress and the
launcher's board excepted; a router forwards everything.  Default deny.
"""

from __future__ import annotations

from .topology import OUTPUT_TOPIC, STAGES

__all__ = ["ROLES", "access_control"]

#: Every identity of a run: a certificate's common name.
ROLES = (*STAGES, "launcher", "control", "router")

#: Messages of a reader (subscribers, queries, liveliness watchers).
_READ = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
#: Messages of a writer: puts, cache replies and queryables, liveliness tokens.
_WRITE = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]
_ALL = _READ + _WRITE


def _keys(*keys: str) -> list[str]:
    """Each key and its advanced-publisher keys (``<key>/@adv/**``: caches, heartbeats,
    publisher tokens; ``@`` chunks are matched by no wildcard)."""
    return [k for key in keys for k in (key, f"{key}/@adv/**")]


def access_control(run: str = "*") -> dict:
    """The ``access_control`` section of a router's Zenoh configuration (see the module
    docstring for who may publish what); ``run``: the run id, or ``*`` for every run."""
    r = f"ttl/{run}"
    everything = _keys(f"{r}/**")
    rules = [
        {"id": "read", "messages": _READ, "flows": ["ingress"], "permission": "allow", "key_exprs": everything},
        # subscriber-detection tokens of advanced subscribers
        {
            "id": "subscriber-tokens",
            "messages": ["liveliness_token"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [f"{r}/**/@adv/sub/**"],
        },
        {"id": "deliver", "messages": _ALL, "flows": ["egress"], "permission": "allow", "key_exprs": everything},
        {"id": "forward", "messages": _ALL, "flows": ["ingress"], "permission": "allow", "key_exprs": everything},
        {
            "id": "commands",
            "messages": ["put"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [f"{r}/control/**"],
        },
        # (the subscriber tokens of a progress subscriber, .../@adv/sub/..., stay allowed)
        {
            "id": "no-forged-progress",
            "messages": _WRITE,
            "flows": ["ingress"],
            "permission": "deny",
            "key_exprs": [f"{r}/control/progress/**", f"{r}/control/progress/**/@adv/pub/**"],
        },
        {
            "id": "launcher-token",
            "messages": ["liveliness_token"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [f"{r}/alive/launcher"],
        },
        # the progress the launcher verified, which the stages follow (docs/operations.md)
        {
            "id": "launcher-board",
            "messages": _WRITE,
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": _keys(f"{r}/control/board/*"),
        },
        {
            "id": "no-forged-board",
            "messages": _WRITE,
            "flows": ["ingress"],
            "permission": "deny",
            "key_exprs": _keys(f"{r}/control/board/*"),
        },
        # a query on a stage's command key is a command: not from another stage
        {
            "id": "no-asked-commands",
            "messages": ["query"],
            "flows": ["ingress"],
            "permission": "deny",
            "key_exprs": [f"{r}/control/{stage}/*" for stage in STAGES],
        },
    ]
    # one subject per common name: a transport matches exactly one subject, so the router
    # logs one decision per message (refusals() relies on it)
    common = ["read", "subscriber-tokens", "deliver"]
    grants = {
        "router": ["forward"],
        "launcher": ["commands", "no-forged-progress", "launcher-token", "launcher-board"],
        "control": ["commands", "no-forged-progress", "no-forged-board"],
    }
    for stage, topic in OUTPUT_TOPIC.items():
        rules.append(
            {
                "id": f"{stage}-publishes",
                "messages": _WRITE,
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": _keys(f"{r}/{topic}", f"{r}/errors/*", f"{r}/control/progress/{stage}")
                + [f"{r}/alive/{stage}"],
            }
        )
        # its commands come as queries (ttl control waits for the verdict): it answers them
        rules.append(
            {
                "id": f"{stage}-answers",
                "messages": ["declare_queryable", "reply"],
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": [f"{r}/control/{stage}/*"],
            }
        )
        grants[stage] = [f"{stage}-publishes", f"{stage}-answers", "no-asked-commands"]
    subjects = [{"id": role, "cert_common_names": [role]} for role in ROLES]
    policies = [{"id": role, "rules": common + grants[role], "subjects": [role]} for role in ROLES]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
