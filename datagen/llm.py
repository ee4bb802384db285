"""An LLM planner over any OpenAI-compatible chat-completions endpoint (`POST {url}/chat/completions`).

SUDD uses a language model to decompose a task and to write each subtask's success check. Here the model
answers two small few-shot prompts (`datagen/prompts/decompose.txt`, `check.txt`); every answer is parsed
and validated before use (the plan against `Plan.validate`, each check against the sandbox's static rules
and the scene's names), and an invalid answer is re-asked with the error appended, so the model can fix
it. Transport failures (timeouts, connection errors, 5xx, 429) back off exponentially with jitter; other
HTTP errors fail at once. Replies are cached on disk by a hash of (messages, model, temperature), not the
URL, so a re-run or another host serving the same model makes no HTTP call. Standard library only.
"""

from __future__ import annotations

import hashlib
import http.client
import json
import os
import random
import re
import textwrap
import time
import urllib.error
import urllib.request
from pathlib import Path

from datagen.checks import subtask_check as template_check
from datagen.checks import task_check as template_task_check
from datagen.plan import Plan, PlanError, SceneDescription, Subtask
from datagen.sandbox import SandboxError, compile_check

API_KEY_ENV = "SUDD_LLM_API_KEY"
PROMPTS = Path(__file__).parent / "prompts"
SYSTEM = "You are a careful robot task planner. Follow the requested answer format exactly."
MAX_SUBTASKS = 20


class LLMError(RuntimeError):
    """The endpoint failed or the model gave no valid answer; the message names the URL and what happened."""


def load_prompt(name: str, **fields: str) -> str:
    """A prompt file with its `{{field}}` placeholders filled (plain replace: the examples hold JSON braces)."""
    text = (PROMPTS / f"{name}.txt").read_text()
    for key, value in fields.items():
        text = text.replace("{{" + key + "}}", value)
    return text


def extract_json(text: str):
    """The first JSON value in a reply, tolerating ```json fences and prose around it."""
    fenced = re.search(r"```[a-zA-Z]*\s*\n?(.*?)```", text, re.S)
    candidate = (fenced.group(1) if fenced else text).strip()
    try:
        return json.loads(candidate)
    except json.JSONDecodeError:
        pass
    starts = [i for i in (candidate.find("["), candidate.find("{")) if i >= 0]
    if not starts:
        raise ValueError("no JSON list or object found in the answer")
    return json.JSONDecoder().raw_decode(candidate[min(starts):])[0]


def parse_subtasks(text: str, scene: SceneDescription, instruction: str = "") -> tuple[Subtask, ...]:
    data = extract_json(text)
    if isinstance(data, dict) and "subtasks" in data:
        data = data["subtasks"]
    if not isinstance(data, list) or not data or len(data) > MAX_SUBTASKS:
        raise PlanError(f"expected a JSON list of 1..{MAX_SUBTASKS} subtasks, got {type(data).__name__}")
    subtasks = []
    for i, item in enumerate(data):
        if not (isinstance(item, dict) and isinstance(item.get("text"), str)
                and isinstance(item.get("primitive"), str) and isinstance(item.get("args"), dict)):
            raise PlanError(f"subtask {i} must be an object with string text, string primitive and object args")
        subtasks.append(Subtask(item["text"], item["primitive"], dict(item["args"])))
    Plan(instruction, tuple(subtasks), "llm").validate(scene)
    return tuple(subtasks)


def parse_check(text: str, scene: SceneDescription) -> str:
    """A check snippet from a reply (a ```python block, JSON {"check": ...} or bare code), statically verified."""
    fenced = re.search(r"```(?:python|py)?[ \t]*\n(.*?)```", text, re.S)
    if fenced:
        code = fenced.group(1)
    else:
        try:
            data = json.loads(text)
            code = data["check"] if isinstance(data, dict) else None
        except (json.JSONDecodeError, KeyError):
            code = None
        if not isinstance(code, str):
            if "def check" not in text:
                raise SandboxError("no `def check():` found in the answer")
            code = text[text.index("def check"):]
    code = textwrap.dedent(code).strip() + "\n"
    compile_check(code, scene)
    return code


class LLMPlanner:
    """Plans through a chat-completions endpoint; `checks="template"` writes checks from templates instead."""

    def __init__(self, url: str, model: str, cache_dir: str | Path | None = None, *, temperature: float = 0.0,
                 timeout: float = 60.0, max_reasks: int = 2, max_attempts: int = 5, backoff_base: float = 1.0,
                 backoff_max: float = 30.0, checks: str = "llm", api_key_env: str = API_KEY_ENV,
                 sleep=time.sleep, seed: int | None = None):
        if checks not in ("llm", "template"):
            raise ValueError(f"checks must be 'llm' or 'template', got {checks!r}")
        self.url, self.model, self.temperature, self.timeout = url.rstrip("/"), model, float(temperature), timeout
        self.endpoint = f"{self.url}/chat/completions"
        self.cache_dir = Path(cache_dir) if cache_dir else None
        self.max_reasks, self.max_attempts = max(0, max_reasks), max(1, max_attempts)
        self.backoff_base, self.backoff_max, self.checks = backoff_base, backoff_max, checks
        self.api_key_env, self.sleep, self.rng = api_key_env, sleep, random.Random(seed)
        self.http_calls = 0  # requests actually sent (cache hits make none)

    @property
    def name(self) -> str:
        return f"llm:{self.model}"

    def plan(self, instruction: str, scene: SceneDescription) -> Plan:
        scene_text = "\n".join(scene.prompt_lines())
        prompt = load_prompt("decompose", instruction=instruction, scene=scene_text)
        subtasks = self.ask(prompt, lambda reply: parse_subtasks(reply, scene, instruction), "plan")
        if self.checks == "template":
            subtasks = tuple(Subtask(s.text, s.primitive, s.args, template_check(s.primitive, s.args, scene))
                             for s in subtasks)
            return Plan(instruction, subtasks, self.name, template_task_check(subtasks, scene)).validate(scene)
        with_checks = []
        for s in subtasks:
            goal = f"{json.dumps(s.text)} (primitive {s.primitive}, args {json.dumps(s.args)})"
            with_checks.append(Subtask(s.text, s.primitive, s.args, self._check(goal, scene_text, scene)))
        goal = f"{json.dumps(instruction)} (the whole task: check its final state)"
        return Plan(instruction, tuple(with_checks), self.name, self._check(goal, scene_text, scene)).validate(scene)

    def _check(self, goal: str, scene_text: str, scene: SceneDescription) -> str:
        prompt = load_prompt("check", goal=goal, scene=scene_text)
        return self.ask(prompt, lambda reply: parse_check(reply, scene), "check")

    def ask(self, prompt: str, parse, what: str):
        """Chat until `parse` accepts a reply, re-asking with the error up to `max_reasks` times."""
        messages = [{"role": "system", "content": SYSTEM}, {"role": "user", "content": prompt}]
        for _ in range(self.max_reasks + 1):
            reply = self.chat(messages)
            try:
                return parse(reply)
            except (PlanError, SandboxError, ValueError, KeyError, TypeError, RecursionError) as e:
                error = f"{type(e).__name__}: {e}"
            messages = messages + [{"role": "assistant", "content": reply},
                                   {"role": "user", "content": f"That answer is invalid: {error}\n"
                                                               "Reply again with a corrected answer only."}]
        raise LLMError(f"{self.endpoint} (model {self.model}): no valid {what} after {self.max_reasks + 1} "
                       f"answers; last error: {error}")

    # -- transport and cache ---------------------------------------------------------------------------
    def cache_key(self, messages: list[dict]) -> str:
        blob = json.dumps({"messages": messages, "model": self.model, "temperature": self.temperature},
                          sort_keys=True, ensure_ascii=True)
        return hashlib.sha256(blob.encode()).hexdigest()

    def chat(self, messages: list[dict]) -> str:
        """The reply's content, from the disk cache when there, else from the endpoint (then cached)."""
        key = self.cache_key(messages)
        path = self.cache_dir / f"{key}.json" if self.cache_dir else None
        if path is not None and path.exists():
            try:
                entry = json.loads(path.read_text())
                if entry.get("model") == self.model and isinstance(entry.get("content"), str):
                    return entry["content"]
            except (OSError, ValueError):
                pass  # a torn or foreign file: ask again and overwrite it
        content = self._post(messages)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps({"model": self.model, "temperature": self.temperature, "messages": messages,
                                       "content": content}, indent=1))
            os.replace(tmp, path)  # atomic: concurrent workers never read half a file
        return content

    def _post(self, messages: list[dict]) -> str:
        body = json.dumps({"model": self.model, "messages": messages, "temperature": self.temperature}).encode()
        headers = {"Content-Type": "application/json", "Accept": "application/json"}
        if os.environ.get(self.api_key_env):
            headers["Authorization"] = f"Bearer {os.environ[self.api_key_env]}"
        failures = []
        for attempt in range(self.max_attempts):
            retry_after = None
            try:
                self.http_calls += 1
                request = urllib.request.Request(self.endpoint, data=body, headers=headers, method="POST")
                with urllib.request.urlopen(request, timeout=self.timeout) as response:
                    payload = response.read()
                return _content(payload, self.endpoint)
            except urllib.error.HTTPError as e:
                detail = e.read(300).decode("utf-8", "replace") if e.fp else ""
                if e.code != 429 and e.code < 500:
                    raise LLMError(f"{self.endpoint}: HTTP {e.code} {e.reason}: {detail}") from None
                failures.append(f"HTTP {e.code} {e.reason}")
                retry_after = e.headers.get("Retry-After") if e.headers else None
            except (urllib.error.URLError, TimeoutError, ConnectionError, http.client.HTTPException, OSError) as e:
                reason = getattr(e, "reason", e)
                failures.append(f"{type(reason).__name__}: {reason}" if str(reason) else type(reason).__name__)
            if attempt + 1 < self.max_attempts:
                delay = min(self.backoff_max, self.backoff_base * 2**attempt) * self.rng.uniform(0.5, 1.0)
                if retry_after and retry_after.strip().replace(".", "", 1).isdigit():
                    delay = max(delay, min(float(retry_after), self.backoff_max))
                self.sleep(delay)
        raise LLMError(f"{self.endpoint}: no answer after {self.max_attempts} attempts "
                       f"(timeout {self.timeout:g} s); failures: {'; '.join(failures)}")


def _content(payload: bytes, endpoint: str) -> str:
    try:
        data = json.loads(payload)
        content = data["choices"][0]["message"]["content"]
    except (ValueError, KeyError, IndexError, TypeError):
        raise LLMError(f"{endpoint}: not a chat-completions response: {payload[:300]!r}") from None
    if not isinstance(content, str):
        raise LLMError(f"{endpoint}: the reply has no text content: {payload[:300]!r}")
    return content
