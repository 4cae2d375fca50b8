"""Agent-tagged log lines and the correction summary."""

from __future__ import annotations

import asyncio
import contextvars
import logging

import pytest

from hivemap.client.logtags import AgentTag, CorrectionSummary, tag_agent


def test_lines_carry_the_agent_of_their_context() -> None:
    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(self.format(record))

    handler = Keep()
    handler.addFilter(AgentTag())
    handler.setFormatter(logging.Formatter("%(agent)s%(message)s"))
    log = logging.getLogger("hivemap.test.tags")
    log.addHandler(handler)
    log.setLevel(logging.INFO)

    async def agent(aid: str) -> None:
        tag_agent(aid)  # each task has its own context: two agents in one process keep their tags
        await asyncio.sleep(0)
        log.info("in loop")
        await asyncio.to_thread(log.info, "in thread")

    async def both() -> None:
        await asyncio.gather(agent("uav1"), agent("ugv1"))

    def main() -> None:
        asyncio.run(both())
        log.info("outside")

    try:
        # an empty context: earlier in-process replays in this test session tagged the main context
        contextvars.Context().run(main)
    finally:
        log.removeHandler(handler)
    assert sorted(records) == sorted(
        ["[uav1] in loop", "[ugv1] in loop", "[uav1] in thread", "[ugv1] in thread", "outside"]
    )


def test_corrections_are_debug_lines_and_a_periodic_summary(caplog: pytest.LogCaptureFixture) -> None:
    log = logging.getLogger("hivemap.test.corrections")
    summary = CorrectionSummary(log, interval_s=3600.0)
    with caplog.at_level(logging.DEBUG, logger="hivemap.test.corrections"):
        for n in (0, 4, 0, 2):
            summary.add(3, "global", n)
        assert [r.levelno for r in caplog.records] == [logging.DEBUG] * 4
        summary.flush()
        summary.flush()  # nothing new: no second summary
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert len(infos) == 1
    assert infos[0].startswith("4 corrections in") and "from map 3: 6 keyframes fused" in infos[0]
    assert "(2 corrections had none of this session's)" in infos[0]
