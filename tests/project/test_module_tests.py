"""Every module of src/rtupoll has its test file: tests/<folder>/test_<name>.py, or
tests/<folder>/test_<folder>_<name>.py where two folders have a module of that name (test
files' names are unique, test_layout.py); a root module's, tests/<any>/test_<name>.py.

A module tested only through another's tests is listed below with the test file that
does it (which must import it), or, with no such file, with why it needs none of its
own; an entry whose module has gained its file, or is gone, fails too."""

from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).parents[1]
SOURCE = TESTS.parent / "src" / "rtupoll"

# module -> the test file that tests it (it imports the module)
TESTED_BY = {
    "config.paths": "config/test_labels.py",
    "config.profile_file": "config/test_hostile_files.py",
    "config.yamlsrc": "config/test_hostile_files.py",
    "gateway.clients": "gateway/test_gateway_server.py",
    "gateway.metrics": "gateway/test_gateway_server.py",
    "gateway.service": "app/test_service_reload.py",
    "io.interface": "config/test_library.py",
    "io.latency": "io/test_port_errors.py",
    "io.taps": "sniff/test_traffic.py",
    "jobs.hole_services": "jobs/test_holes.py",
    "jobs.services": "app/test_service_reload.py",
    "model.carried": "cli/test_decode.py",
    "model.interpret": "config/test_library.py",
    "model.profile": "config/test_library.py",
    "outputs.fleet": "web/test_state.py",
    "rtu.functions": "cli/test_send.py",
    "rtu.match": "cli/test_send.py",
    "sim.engine": "config/test_library.py",
    "sim.runner": "app/test_service_reload.py",
    "sim.virtual": "io/test_virtual_bus.py",
    "sniff.lines": "sniff/test_model.py",
    "sniff.render": "sniff/test_model.py",
    "sniff.session": "sniff/test_sniff_fuzz.py",
    "ui.logs": "jobs/test_reload_service.py",
    "ui.systemd": "app/test_services.py",
    "web.service": "app/test_services.py",
}

# module -> why no test file imports it: it is run through what uses it
THROUGH = {
    "aio": "two asyncio helpers (a task group, a signal); every async command runs them",
    "cli.doctor": "click wiring of `doctor`: jobs/test_doctor.py runs the command",
    "cli.guess": "click wiring of `guess`: model/test_guess.py runs the command",
    "cli.options": "options shared by the commands: every CLI test passes them",
    "cli.params": "click parameter types: every CLI test passes them",
    "cli.profiles": "click wiring of `profiles`: config/test_profiles_check.py runs it",
    "cli.scan": "click wiring of `scan`: jobs/test_scan_sim.py and config/test_library.py",
    "cli.serve_options": "the gateway's options: gateway/test_gateway_cli.py passes them",
    "cli.simulate": "click wiring of `simulate`: sim/test_sim_cli.py runs the command",
    "cli.sniff": "click wiring of `sniff`: sniff/test_sniff.py runs the command",
    "cli.target": "--port/--config to a bus: every CLI test that polls goes through it",
    "cli.web": "click wiring of `web`: web/test_web_http.py runs the command",
    "config.ha_yaml": "Home Assistant's YAML tags: config/test_ha_import.py loads files with them",
    "config.idle_gap": "the idle_gap key: config/test_site.py loads profiles and site files "
                       "that set it",
    "config.listen": "the listen-address rule: the --http/--serve/--metrics tests parse with it",
    "config.telegraf_import": "config/test_import_corpus.py imports Telegraf files through it",
    "gateway.footer": "the gateway's status line: gateway/test_gateway_sim.py runs the gateway",
    "jobs.histogram": "reply-time buckets: outputs/test_prometheus.py checks the exported ones",
    "model.identify": "identify checks: config/test_library.py scans, sniff/test_sniff.py sniffs",
    "sim.consistent": "related simulated values: sim/test_values.py checks what it makes",
    "sniff.port": "the sniffer's port reader: sniff/test_sniff.py sniffs ptys through it",
    "web.options": "the dashboard's options: web/test_web_http.py starts it with them",
}


def modules() -> dict[str, Path]:
    return {".".join(p.relative_to(SOURCE).with_suffix("").parts): p
            for p in sorted(SOURCE.rglob("*.py")) if p.stem not in ("__init__", "__main__")}


def has_own_file(module: str) -> bool:
    *folder, name = module.split(".")
    if not folder:
        return any(TESTS.glob(f"*/test_{name}.py"))
    where = TESTS / folder[0]
    return (where / f"test_{name}.py").exists() or (where / f"test_{folder[0]}_{name}.py").exists()


def test_every_module_has_its_test_file_or_says_why_not() -> None:
    missing = [m for m in modules() if not has_own_file(m) and m not in TESTED_BY | THROUGH]
    assert not missing, f"modules with no tests/<folder>/test_<name>.py: {missing}"


def test_the_list_of_modules_tested_through_others_is_current() -> None:
    have = modules()
    listed = TESTED_BY | THROUGH
    assert not set(TESTED_BY) & set(THROUGH)
    stale = [m for m in listed if m not in have or has_own_file(m)]
    assert not stale, f"entries to remove (the module has its file now, or is gone): {stale}"
    for module, test in TESTED_BY.items():
        parent, _, name = f"rtupoll.{module}".rpartition(".")
        text = (TESTS / test).read_text()
        assert re.search(rf"(from|import) rtupoll\.{re.escape(module)}\b"
                         rf"|from {re.escape(parent)} import [^\n]*\b{name}\b", text), (
            f"{test} does not import rtupoll.{module}")
    for module, why in THROUGH.items():
        for test in re.findall(r"[a-z]+/test_[a-z_]+\.py", why):
            assert (TESTS / test).exists(), f"{module}: {test} is gone"
