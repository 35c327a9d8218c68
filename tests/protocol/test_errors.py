"""The error hierarchy: each error class has its own code, and a code (from an ErrorReply)
rebuilds its class.
"""

from __future__ import annotations

import inspect

import pytest

from overtake.protocol import errors
from overtake.protocol.codec import decode, encode
from overtake.protocol.errors import ERRORS_BY_CODE, ProtocolError, error_from_code
from overtake.protocol.messages import ErrorReply


@pytest.mark.parametrize("code, cls", sorted(ERRORS_BY_CODE.items()))
def test_error_from_code_rebuilds_the_class_with_that_code(code, cls):
    error = error_from_code(code, "the server's own words")
    assert type(error) is cls
    assert error.code == code
    assert str(error) == "the server's own words"
    # Through the wire, as the client does with an ErrorReply.
    reply = decode(encode(ErrorReply(code=code, message="m")))
    assert type(error_from_code(reply.code, reply.message)) is cls


def test_error_from_an_unknown_code_is_the_base_class():
    error = error_from_code("added_by_a_newer_peer", "m")
    assert type(error) is ProtocolError and str(error) == "m"


def test_every_error_class_has_its_own_code():
    # Two classes sharing a code would silently drop one from ERRORS_BY_CODE.
    classes = [
        obj
        for obj in vars(errors).values()
        if inspect.isclass(obj) and issubclass(obj, ProtocolError)
    ]
    assert sorted(ERRORS_BY_CODE.values(), key=lambda c: c.__name__) == sorted(
        classes, key=lambda c: c.__name__
    )
    assert all(issubclass(cls, ProtocolError) for cls in ERRORS_BY_CODE.values())
