"""The multi-process test helpers' own behaviour (fullperc_common.testing)."""

import pytest

from fullperc_common.testing import wait_for


def test_wait_for_appends_the_detail_to_a_timeout_and_calls_it_only_then():
    calls = []

    def detail():
        calls.append(1)
        return "the peer had done nothing"

    assert wait_for(lambda: 7, 1.0, detail=detail) == 7
    assert calls == []
    with pytest.raises(pytest.fail.Exception, match=r"waiting for the peer: the peer had done nothing$"):
        wait_for(lambda: False, 0.01, interval=0.001, what="the peer", detail=detail)
    assert calls == [1]
    with pytest.raises(pytest.fail.Exception, match=r"waiting for the peer$"):
        wait_for(lambda: False, 0.01, interval=0.001, what="the peer")
