"""callback_url checks at submission (service.webhooks.vet): IPv6 forms that carry or reach an IPv4 address are
judged by where a delivery would end up, and a URL with a character HTTP cannot send (CR, LF, a space, a control
or non-ASCII character) is refused, not accepted and then never delivered."""

from __future__ import annotations

import pytest
from stack import assert_error, make_settings, post
from test_webhooks import BALL, SECRET, Receiver, fixed, hooks_settings

from fastmesh_jobs.store import Store
from service.processes import ServedApp
from service.webhooks import UnsafeUrl, is_public, vet


@pytest.fixture(scope="module")
def idle(redis_url):
    """An app that calls plain http and loopback addresses too (webhook_allow_private), with no worker."""
    app = ServedApp(hooks_settings(redis_url, "hooks-chars"))
    yield app
    app.stop()


@pytest.fixture()
def receiver():
    r = Receiver()
    yield r
    r.close()


@pytest.fixture(scope="module")
def strict(redis_url):
    """An app that calls https and public addresses only (webhook_allow_private off, as deployed)."""
    app = ServedApp(make_settings(redis_url, "hooks-strict-app", webhook_secret=SECRET))
    yield app
    app.stop()


# IPv6 forms that carry a loopback, private or link-local (cloud metadata) IPv4 address, or tunnel to the IPv4
# address they hold (6to4, Teredo), or that are never public.
EMBEDDING = ["64:ff9b::7f00:1", "64:ff9b::a9fe:a9fe", "64:ff9b::a00:1", "64:ff9b:1::7f00:1", "64:ff9b:1:7f00:1::",
             "64:ff9b:1:808:808::", "2002:7f00:1::1", "2002:a9fe:a9fe::1", "2002:c0a8:101::", "2002:808:808::1",
             "::127.0.0.1", "::8.8.8.8", "::ffff:0:7f00:1", "::ffff:0:a9fe:a9fe", "fec0::1", "fec0::7f00:1",
             "2001:0:4136:e378:8000:63bf:3fff:fdd2"]


@pytest.mark.parametrize("address", EMBEDDING)
def test_ipv6_forms_reaching_a_non_public_or_tunnelled_ipv4_address_are_refused(strict, address):
    assert not is_public(address)
    with pytest.raises(UnsafeUrl, match="non-public"):  # a name resolving to it (AAAA)
        vet("https://hooks.example.com/x", False, fixed(address))
    r = post(strict.url, "ball.xyz", BALL, callback_url=f"https://[{address}]/x")  # the literal, at submission
    err = assert_error(r, 422, "invalid_parameter")
    assert err["message"].startswith("callback_url: ") and "non-public" in err["message"], err


@pytest.mark.parametrize("address", ["64:ff9b::808:808", "::ffff:0:808:808", "::ffff:8.8.8.8", "2606:4700:4700::1111"])
def test_ipv6_forms_of_public_addresses_pass(address):
    assert is_public(address)
    assert vet(f"https://[{address}]:8443/x", False) == (address, 8443, address)


@pytest.mark.parametrize("suffix", ["\r\nX-Evil: 1", "\n", "\r", "\t", " x", "?a=\x01", "/\x7f", "/h\u00e9"])
def test_a_callback_url_with_a_raw_control_space_or_non_ascii_character_is_refused(idle, receiver, suffix):
    """It could never be sent (HTTP has no way to carry it): refused at submission, naming the character."""
    store = Store(idle.settings)
    before = store.redis.zcard(store.k_queued)
    r = post(idle.url, "ball.xyz", BALL, callback_url=receiver.url + suffix)
    err = assert_error(r, 422, "invalid_parameter")
    bad = next(c for c in suffix if not "!" <= c <= "~")
    assert err["message"].startswith("callback_url: character ") and f" is {bad!r}: " in err["message"], err
    assert "percent-encode" in err["message"]
    assert store.redis.zcard(store.k_queued) == before  # no job made

