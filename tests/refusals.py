"""One helper of the tests of refusals: the call raises an InputError whose message holds given words."""

from __future__ import annotations

import pytest

from crfdepth.errors import InputError


def refused(call, *words) -> str:
    """The message of the :class:`~crfdepth.errors.InputError` that ``call()`` raises; each of ``words`` in it."""
    with pytest.raises(InputError) as info:
        call()
    message = str(info.value)
    for word in words:
        assert word in message, (word, message)
    return message
