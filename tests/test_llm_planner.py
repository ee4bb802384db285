"""The LLM planner against a loopback OpenAI-compatible endpoint: good and fenced answers, re-asking after
malformed JSON or a hostile check, backoff on 500/429, a fast LLMError on a silent server, and the cache."""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from datagen.llm import LLMError, LLMPlanner, extract_json
from datagen.plan import SceneDescription, SceneObject
from datagen.planner import OfflinePlanner, make_planner

SCENE = SceneDescription((SceneObject("obj0", "red block", "object"), SceneObject("obj1", "blue cylinder", "object"),
                          SceneObject("cabinet", "drawer", "articulated", joint="cabinet/slide"),
                          SceneObject("table", "table", "surface")))
INSTRUCTION = "put the red block in the drawer and close it"
REFERENCE = OfflinePlanner().plan(INSTRUCTION, SCENE)  # what a perfect model would answer
PLAN_JSON = json.dumps([{"text": s.text, "primitive": s.primitive, "args": s.args} for s in REFERENCE.subtasks])
HOSTILE = "```python\ndef check():\n    return __import__('os').system('echo pwned') == 0\n```"


def good_answer(messages: list[dict]) -> str:
    prompt = messages[1]["content"]
    if "Answer with JSON only" in prompt:
        return PLAN_JSON
    goal = prompt.rsplit("Goal:", 1)[1]
    for s in REFERENCE.subtasks:
        if json.dumps(s.text) in goal:
            return f"Here you go:\n```python\n{s.check}```"
    return f"```python\n{REFERENCE.task_check}```"


class FakeEndpoint:
    """A chat-completions server on 127.0.0.1; `script` holds canned behaviours consumed one per request."""

    def __init__(self):
        self.requests, self.script, self.release = [], [], threading.Event()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                outer.requests.append({"path": self.path, "body": body, "auth": self.headers.get("Authorization")})
                action = outer.script.pop(0) if outer.script else ("answer", None)
                if action[0] == "hang":
                    outer.release.wait(10)
                    return
                if action[0] == "status":
                    self.send_response(action[1])
                    self.send_header("Retry-After", "0")
                    self.end_headers()
                    self.wfile.write(b'{"error": "busy"}')
                    return
                content = action[1] if action[0] == "raw" else good_answer(body["messages"])
                reply = json.dumps({"id": "x", "object": "chat.completion", "model": body["model"],
                                    "choices": [{"index": 0, "finish_reason": "stop",
                                                 "message": {"role": "assistant", "content": content}}]}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(reply)))
                self.end_headers()
                self.wfile.write(reply)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/v1"
        self.thread = threading.Thread(target=self.server.serve_forever, args=(0.02,), daemon=True)
        self.thread.start()

    def close(self):
        self.release.set()
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def endpoint(monkeypatch):
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")
    monkeypatch.delenv("SUDD_LLM_API_KEY", raising=False)
    server = FakeEndpoint()
    yield server
    server.close()


def planner(endpoint, tmp_path, **kw) -> LLMPlanner:
    sleeps = []
    options = dict(timeout=5.0, backoff_base=0.01, backoff_max=0.05, sleep=sleeps.append, seed=0)
    p = LLMPlanner(endpoint.url, "test-model", cache_dir=tmp_path / "cache", **{**options, **kw})
    p.sleeps = sleeps
    return p


def test_good_answers_make_the_same_plan_as_the_offline_parser(endpoint, tmp_path, monkeypatch):
    monkeypatch.setenv("SUDD_LLM_API_KEY", "sk-test")
    plan = planner(endpoint, tmp_path).plan(INSTRUCTION, SCENE)
    assert plan.planner == "llm:test-model"
    assert plan.subtasks == REFERENCE.subtasks and plan.task_check == REFERENCE.task_check
    assert len(endpoint.requests) == 1 + 4 + 1  # decompose, a check per subtask, the task's check
    first = endpoint.requests[0]
    assert first["path"] == "/v1/chat/completions" and first["auth"] == "Bearer sk-test"
    assert first["body"]["model"] == "test-model" and first["body"]["temperature"] == 0
    assert "- obj0: red block (object)" in first["body"]["messages"][1]["content"]


def test_fenced_json_and_template_checks(endpoint, tmp_path):
    endpoint.script = [("raw", f"Sure!\n```json\n{PLAN_JSON}\n```\nLet me know.")]
    plan = planner(endpoint, tmp_path, checks="template").plan(INSTRUCTION, SCENE)
    assert plan.subtasks == REFERENCE.subtasks and len(endpoint.requests) == 1
    assert endpoint.requests[0]["auth"] is None


def test_malformed_json_is_reasked_with_the_error(endpoint, tmp_path):
    endpoint.script = [("raw", "[{\"text\": \"open the drawer\", "), ("raw", json.dumps([{"text": "x",
                       "primitive": "fly", "args": {}}]))]
    plan = planner(endpoint, tmp_path, checks="template").plan(INSTRUCTION, SCENE)
    assert plan.subtasks == REFERENCE.subtasks and len(endpoint.requests) == 3
    second, third = (r["body"]["messages"] for r in endpoint.requests[1:])
    assert second[2] == {"role": "assistant", "content": "[{\"text\": \"open the drawer\", "}
    assert "invalid" in second[3]["content"] and "JSONDecodeError" in second[3]["content"]
    assert "unknown primitive 'fly'" in third[-1]["content"]


def test_a_hostile_check_is_rejected_and_reasked(endpoint, tmp_path):
    endpoint.script = [("answer", None), ("raw", HOSTILE)]
    plan = planner(endpoint, tmp_path).plan(INSTRUCTION, SCENE)
    assert plan.subtasks == REFERENCE.subtasks
    reask = endpoint.requests[2]["body"]["messages"]
    assert "SandboxError: attribute access is not allowed (line 2)" in reask[-1]["content"]


def test_a_model_that_stays_hostile_fails_with_llm_error(endpoint, tmp_path):
    endpoint.script = [("answer", None)] + [("raw", HOSTILE)] * 3
    with pytest.raises(LLMError, match=r"/v1/chat/completions \(model test-model\): no valid check after 3 "
                                       r"answers; last error: SandboxError: attribute access"):
        planner(endpoint, tmp_path, max_reasks=2).plan(INSTRUCTION, SCENE)
    assert len(endpoint.requests) == 4


def test_server_errors_and_rate_limits_back_off_then_succeed(endpoint, tmp_path):
    endpoint.script = [("status", 500), ("status", 429), ("status", 503)]
    p = planner(endpoint, tmp_path, checks="template")
    assert p.plan(INSTRUCTION, SCENE).subtasks == REFERENCE.subtasks
    assert len(endpoint.requests) == 4 and len(p.sleeps) == 3
    for attempt, delay in enumerate(p.sleeps):  # exponential with jitter in [0.5, 1] of the step, capped
        assert 0.5 * min(0.05, 0.01 * 2**attempt) <= delay <= min(0.05, 0.01 * 2**attempt)


def test_persistent_errors_name_the_url_and_what_happened(endpoint, tmp_path):
    endpoint.script = [("status", 500)] * 3
    with pytest.raises(LLMError, match=r"127\.0\.0\.1:\d+/v1/chat/completions: no answer after 3 attempts.*"
                                       r"HTTP 500"):
        planner(endpoint, tmp_path, max_attempts=3).plan(INSTRUCTION, SCENE)
    endpoint.script = [("status", 401)]
    with pytest.raises(LLMError, match="HTTP 401"):
        planner(endpoint, tmp_path).plan(INSTRUCTION, SCENE)
    assert len(endpoint.requests) == 4  # a 4xx other than 429 is not retried


def test_a_silent_server_times_out_quickly(endpoint, tmp_path):
    endpoint.script = [("hang",)] * 2
    t0 = time.perf_counter()
    with pytest.raises(LLMError, match=r"no answer after 2 attempts \(timeout 0\.2 s\).*[Tt]imeout"):
        planner(endpoint, tmp_path, timeout=0.2, max_attempts=2).plan(INSTRUCTION, SCENE)
    assert time.perf_counter() - t0 < 3.0


def test_nothing_listening_is_an_llm_error(tmp_path, monkeypatch):
    monkeypatch.setenv("no_proxy", "127.0.0.1")
    dead = LLMPlanner("http://127.0.0.1:9/v1", "m", tmp_path, max_attempts=2, backoff_base=0.001, timeout=1)
    with pytest.raises(LLMError, match=r"http://127\.0\.0\.1:9/v1/chat/completions: no answer after 2 attempts"):
        dead.plan(INSTRUCTION, SCENE)


def test_cache_hit_makes_no_request_even_from_another_url(endpoint, tmp_path):
    first = planner(endpoint, tmp_path).plan(INSTRUCTION, SCENE)
    sent = len(endpoint.requests)
    again = planner(endpoint, tmp_path).plan(INSTRUCTION, SCENE)
    moved = LLMPlanner("http://127.0.0.1:9/v1", "test-model", tmp_path / "cache", max_attempts=1)
    assert again == first == moved.plan(INSTRUCTION, SCENE)
    assert len(endpoint.requests) == sent and moved.http_calls == 0
    other_model = planner(endpoint, tmp_path, checks="template")
    other_model.model = "another-model"
    other_model.plan(INSTRUCTION, SCENE)
    assert len(endpoint.requests) == sent + 1  # the model is part of the key
    assert len(list((tmp_path / "cache").glob("*.json"))) == sent + 1


def test_extract_json_and_make_planner(tmp_path):
    assert extract_json('noise {"subtasks": [1]} trailing') == {"subtasks": [1]}
    assert extract_json("```\n[1, 2]\n```") == [1, 2]
    with pytest.raises(ValueError, match="no JSON"):
        extract_json("no json here")
    p = make_planner("llm", llm_url="http://h:1/v1/", llm_model="m", cache_dir=tmp_path)
    assert isinstance(p, LLMPlanner) and p.endpoint == "http://h:1/v1/chat/completions" and p.name == "llm:m"
