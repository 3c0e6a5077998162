"""``aesop bench reasoner --llm local``: which prompt a small local model follows.

The bundled SmolLM2-135M-Instruct (or ``--llm-model FILE``) on llama-cpp-python's server
(:mod:`tools.local_llm`, 2 threads), asked by the reasoner's own decider the questions of
the paper's hardware scenarios: for each anomalous scenario of :mod:`tools.scenes.hardware`,
the scene as the camera reports it at the anomaly's spot, the scene's recovery regions
offered beside "continue", and the answer the scenario expects (``expected_decision``). The
verdict's unusual detections are not quoted (they need the detector's cache), so the model
sees the scene as text alone. And the synthetic domains' samples (warehouse, vehicle, VTOL;
``domain_samples`` anomalies and as many nominal scenes each, seeded), with the domain's own
prompt and two options, "continue" or "stop": an anomaly's right answer is to stop (the
domains' anomalies are overtly abnormal, a smoking battery on the belt), a nominal scene's
(a false alarm reaching the reasoner) to continue.

Per template (the chain-of-thought or single-answer prompt, free text or JSON mode with the
options as an ``enum``; ``single-json-first``: the answer before the reasoning, the stream
ended once it is out), ``repeats`` times each case, at temperature 0 and not streamed (so
the server reports its token counts; the answer-first template is streamed, it ends the
stream):

- **parse errors**: decisions whose source is ``parse_error`` (no valid final answer);
- **timeouts**: no answer within ``deadline_s``; **right**: the expected option;
- **continue when a recovery was expected**: the unsafe kind of wrong (the fallback never
  picks it; the robot would fly on);
- latency p50 / p99 / max of the whole decision, and generated tokens per second.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from services.control.core.outbox import options_for
from services.control.core.scenario import load_scenario
from services.reasoner.api import build_decider
from services.reasoner.backends import Completion
from services.reasoner.settings import ReasonerSettings
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest
from shared.tables import table
from tools import progress
from tools.local_llm import REASONER_SETTINGS, THREADS, LocalModel, served
from tools.scenes.hardware import SCENARIOS, observation_text
from tools.scenes.registry import generate
from tools.stack.up import hardware_scenario

TASK = "landing on the red box"
# name -> (prompt variant, JSON mode, the answer first and the stream ended after it)
TEMPLATES: Mapping[str, tuple[str, bool, bool]] = {
    "cot": ("cot", False, False), "single": ("single", False, False),
    "cot-json": ("cot", True, False), "single-json": ("single", True, False),
    "single-json-first": ("single", True, True)}


SYNTHETIC = ("warehouse", "vehicle", "vtol")
STOP = (Option(index=0, label="continue", description="carry on with the task"),
        Option(index=1, label="stop", description="stop safely and wait for an operator"))


@dataclass(frozen=True)
class Case:
    name: str
    request: ReasonerRequest
    expected: int  # the option index the scenario expects
    domain: str = "quadrotor"  # the reasoner's prompt template


@dataclass(frozen=True)
class Answer:
    template: str
    case: str
    decision: ReasonerDecision
    expected: int
    completion_tokens: int | None
    seconds: float


def hardware_cases(deadline_s: float) -> list[Case]:
    """The anomalous hardware scenarios as the reasoner would be asked at their spot."""
    scene = load_scenario(hardware_scenario())
    options = options_for(scene.regions, [r.index for r in scene.regions])
    by_label = {o.label: o.index for o in options}
    cases = []
    for s in SCENARIOS:
        if s.expected_decision is None or s.spot is None:
            continue
        text = observation_text(s.detections((*s.spot, 1.0)))
        request = ReasonerRequest(
            request_id=s.name, deadline_s=deadline_s, options=options,
            observation=Observation(seq=1, task=TASK, text=text))
        cases.append(Case(s.name, request, by_label[s.expected_decision]))
    return cases


def domain_cases(per_domain: int, deadline_s: float, seed: int = 0) -> list[Case]:
    """``per_domain`` anomalies and nominal scenes of each synthetic domain (module
    docstring), as its robot would publish them (the task and the detections, brief)."""
    cases = []
    for name in SYNTHETIC:
        data = generate(name, seed=seed, n_nominal=per_domain, n_anomaly=per_domain)
        for i, sample in enumerate(data.samples):
            anomaly = sample.label == "anomaly"
            request = ReasonerRequest(
                request_id=f"{name}-{i}", deadline_s=deadline_s, options=STOP,
                observation=Observation(seq=1, task=sample.task, text=sample.observation))
            cases.append(Case(f"{name}-{'anomaly' if anomaly else 'nominal'}-{i}", request,
                              int(anomaly), name))
    return cases


async def ask(url: str, model: LocalModel, template: str, cases: Sequence[Case],
              repeats: int) -> list[Answer]:
    variant, json_mode, first = TEMPLATES[template]
    # streamed only when the answer comes first (it ends the stream); else whole, so that
    # the server reports its token counts
    request = {**REASONER_SETTINGS["request"], "stream": first, "json_schema": json_mode,
               "answer_first": first}
    tokens: list[Completion] = []
    deciders = {domain: build_decider(ReasonerSettings(
        llm_base_url=url, llm_model=model.alias, variant=variant, request=request,
        domain=domain), tokens.append) for domain in dict.fromkeys(c.domain for c in cases)}
    answers = []
    try:
        for _ in range(repeats):
            for case in cases:
                tokens.clear()
                t0 = time.perf_counter()
                decision = await deciders[case.domain].decide(case.request)
                seconds = time.perf_counter() - t0
                used = tokens[0].completion_tokens if tokens else None
                answers.append(Answer(template, case.name, decision, case.expected, used,
                                      seconds))
                progress.count(len(answers), repeats * len(cases), "answers")
    finally:
        for decider in deciders.values():
            await decider.aclose()
    return answers


def case_set(name: str) -> str:
    """The set a case belongs to: ``hardware``, or a synthetic domain's anomalies or
    nominal scenes."""
    domain = name.split("-", 1)[0]
    if domain not in SYNTHETIC:
        return "hardware"
    return f"{domain} {'anomalies' if '-anomaly-' in name else 'nominal'}"


def _right(answer: Answer) -> bool:
    return answer.decision.source == "llm" and answer.decision.choice == answer.expected


def summarise(answers: Sequence[Answer]) -> dict[str, Any]:
    """Per template: counts, accuracy, latency and token rate (see the module docstring)."""
    out: dict[str, Any] = {}
    for template in dict.fromkeys(a.template for a in answers):
        mine = [a for a in answers if a.template == template]
        ms = np.asarray([a.decision.latency_ms for a in mine])
        rates = [a.completion_tokens / a.seconds for a in mine
                 if a.completion_tokens and a.decision.source == "llm"]
        out[template] = {
            "n": len(mine),
            "parse_errors": sum(a.decision.source == "parse_error" for a in mine),
            "timeouts": sum(a.decision.source == "timeout" for a in mine),
            "backend_errors": sum(a.decision.source == "backend_error" for a in mine),
            "right": sum(map(_right, mine)),
            "right_by_set": {group: f"{sum(map(_right, these))}/{len(these)}"
                             for group in dict.fromkeys(case_set(a.case) for a in mine)
                             if (these := [a for a in mine if case_set(a.case) == group])},
            "continue_when_recovery_expected": sum(
                a.decision.source == "llm" and a.decision.choice == 0 and a.expected != 0
                for a in mine),
            "latency_ms": {"p50": float(np.percentile(ms, 50)),
                           "p99": float(np.percentile(ms, 99)), "max": float(ms.max())},
            "tokens_per_s_p50": float(np.median(rates)) if rates else None,
            "choices": {case: sorted({a.decision.choice for a in mine if a.case == case})
                        for case in dict.fromkeys(a.case for a in mine)},
        }
    return out


def run_templates_bench(model: LocalModel, *, repeats: int = 3, deadline_s: float = 60.0,
                        templates: Sequence[str] = tuple(TEMPLATES), logs: Path,
                        domain_samples: int = 2, threads: int = THREADS) -> dict[str, Any]:
    cases = hardware_cases(deadline_s) + domain_cases(domain_samples, deadline_s)
    with served(model, logs, threads=threads) as url:
        httpx.get(f"{url}/models", timeout=30).raise_for_status()
        answers = []
        for n, template in enumerate(templates, 1):
            progress.step(f"template {template}: {repeats} x {len(cases)} cases", n,
                          len(templates))
            answers += asyncio.run(ask(url, model, template, cases, repeats))
    return {"model": model.alias, "path": str(model.path), "threads": threads, "repeats": repeats,
            "deadline_s": deadline_s, "domain_samples": domain_samples,
            "cases": {c.name: c.expected for c in cases},
            "templates": summarise(answers),
            "answers": [{"template": a.template, "case": a.case, "source": a.decision.source,
                         "choice": a.decision.choice, "expected": a.expected,
                         "latency_ms": a.decision.latency_ms,
                         "completion_tokens": a.completion_tokens,
                         "rationale": a.decision.rationale[:300]} for a in answers]}


def render(result: Mapping[str, Any]) -> str:
    rows = []
    for name, t in result["templates"].items():
        rows.append({"template": name, "n": t["n"], "right": t["right"],
                     "right by set": " ".join(f"{k}:{v}" for k, v in t["right_by_set"].items()),
                     "continue (unsafe)": t["continue_when_recovery_expected"],
                     "parse errors": t["parse_errors"], "timeouts": t["timeouts"],
                     "p50 s": t["latency_ms"]["p50"] / 1e3, "p99 s": t["latency_ms"]["p99"] / 1e3,
                     "tokens/s": t["tokens_per_s_p50"],
                     "hardware choices": " ".join(
                         f"{c.split('-', 1)[0]}:{'/'.join(map(str, v))}"
                         for c, v in t["choices"].items() if case_set(c) == "hardware")})
    expected = ", ".join(f"{k.split('-', 1)[0]} -> {v}" for k, v in result["cases"].items()
                         if case_set(k) == "hardware")
    return table(f"{result['model']} on llama.cpp (2 threads), {result['repeats']} x each "
                 f"case, deadline {result['deadline_s']:g} s; hardware expected: {expected}; "
                 f"{result['domain_samples']} anomalies (stop: 1) and nominal scenes "
                 f"(continue: 0) of each synthetic domain", rows)
