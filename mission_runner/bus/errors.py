"""Errors raised by the vehicle-to-vehicle message bus.

Exception tree::

    MissionRunnerError
    └── BusError
        ├── BusTimeoutError      a bounded wait (receive, subscribe acknowledgement) ran out;
        │                        ``what`` names the wait, ``timeout_s`` its bound
        ├── BusConnectionError   no usable broker connection: refused, lost, credentials
        │                        rejected, not re-established within the publish timeout,
        │                        or the bus is closed
        ├── MessageDecodeError   a payload is not a valid message of the expected type
        ├── MessageValueError    a message was built with a field of the wrong type or out of
        │                        range (a bug on the sending side; also a ``ValueError``)
        ├── BusAuthError         no usable bus key or broker credentials (missing, unreadable,
        │                        too short): found before anything connects
        └── TopicError           a topic or subscription pattern is malformed or does not
                                 fit the mission's topic layout (also a ``ValueError``)

Callers of ``publish`` decide what a ``BusConnectionError`` means for them: a vehicle
controller drops that step's message (its neighbours difference cumulative odometry, so a
lost message costs nothing but freshness); a ground station may retry.
"""

from mission_runner.errors import MissionRunnerError


class BusError(MissionRunnerError):
    """Base class of every error the bus raises on purpose."""


class BusTimeoutError(BusError):
    """A bounded wait on the bus ended without the awaited event.

    ``what`` says what was awaited (e.g. ``"receive on enclosing/m1/vehicle/+/step"``),
    ``timeout_s`` the bound that ran out.
    """

    def __init__(self, what: str, timeout_s: float, hint: str = "") -> None:
        self.what = what
        self.timeout_s = timeout_s
        message = f"{what} timed out after {timeout_s:g} s"
        if hint:
            message += f"; {hint}"
        super().__init__(message)


class BusConnectionError(BusError):
    """The bus cannot reach its broker (or is closed), so the operation was not done.

    ``endpoint`` is ``"host:port"`` for a broker bus and ``"in-process"`` otherwise;
    ``reason`` is the underlying cause in words.
    """

    def __init__(self, endpoint: str, reason: str, hint: str = "") -> None:
        self.endpoint = endpoint
        self.reason = reason
        self.hint = hint
        message = f"bus {endpoint}: {reason}"
        if hint:
            message += f"; {hint}"
        super().__init__(message)


class MessageDecodeError(BusError):
    """A payload could not be decoded into the expected message type.

    ``message_type`` is the expected class name and ``problem`` what was wrong. Subscriber
    loops catch this, count it and carry on: one bad payload never stops a vehicle.
    """

    def __init__(self, message_type: str, problem: str) -> None:
        self.message_type = message_type
        self.problem = problem
        super().__init__(
            f"cannot decode {message_type}: {problem}; "
            "check that the publisher runs the same mission_runner message version"
        )


class MessageValueError(BusError, ValueError):
    """A message object was constructed with a field of the wrong type or out of range."""

    def __init__(self, message_type: str, problem: str) -> None:
        self.message_type = message_type
        self.problem = problem
        super().__init__(f"invalid {message_type}: {problem}")


class TopicError(BusError, ValueError):
    """A topic or subscription pattern is malformed or outside the mission's layout."""


class BusAuthError(BusError):
    """The bus cannot authenticate: no key for an MQTT bus, an unreadable or short key, or
    broker credentials that cannot be found. The message says where a key or credentials go."""

    def __init__(self, problem: str, hint: str = "") -> None:
        self.problem = problem
        self.hint = hint
        super().__init__(f"{problem}; {hint}" if hint else problem)
