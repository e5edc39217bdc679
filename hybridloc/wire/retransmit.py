"""When a client resends: an adaptive retransmission timeout, TCP's (RFC 6298), for the go-back-N uplink.

A fixed resend delay turns a slow server into an overloaded one: when acknowledgements take longer
than the delay (a queue on the server, a backlog after an outage), every device resends everything
in flight, the server decodes and refuses each copy as a duplicate, and the queue grows (a 1,000-client
load run with a fixed 2 s delay sent 152,388 resends for 30,000 batches, five copies of each). TCP's
answer is the one used here:

* the round-trip time is measured on acknowledgements of batches sent once (Karn's rule: a batch that
  was resent gives no sample, since its ack may answer either copy), smoothed as RFC 6298 section 2::

      first sample R:   SRTT = R,  RTTVAR = R / 2
      later samples:    RTTVAR = (1 - beta) RTTVAR + beta |SRTT - R|,   beta = 1/4
                        SRTT   = (1 - alpha) SRTT + alpha R,            alpha = 1/8
      RTO = clamp(SRTT + 4 RTTVAR, min_rto, max_rto)

* after a timeout the RTO doubles (section 5.5, back-off) up to ``max_rto``, until an ack brings a new
  sample.

``min_rto`` is the client's ``resend_after`` (the delay it used to have, so a lost message on an idle
network is still resent that fast); ``max_rto`` bounds how long a client waits to find out that a
restarted server lost its message (RFC 6298 allows 60 s; :data:`MAX_RTO_S` keeps "back within
seconds" after a restart).
"""

from __future__ import annotations

import math

#: Longest wait before a resend, s: after a server restart, a client's next resend comes within this.
MAX_RTO_S = 8.0

ALPHA = 1.0 / 8.0  # RFC 6298 (2.3)
BETA = 1.0 / 4.0
K = 4.0


class RetransmitTimer:
    """The retransmission timeout of one sender, s (:attr:`rto`); RFC 6298 (module docstring)."""

    def __init__(self, min_rto: float, max_rto: float = MAX_RTO_S):
        if not (math.isfinite(min_rto) and min_rto >= 0.0):
            raise ValueError(f"min_rto must be a finite number of seconds >= 0, got {min_rto!r}")
        self.min_rto = float(min_rto)
        self.max_rto = max(float(max_rto), self.min_rto)
        self.srtt: float | None = None
        self.rttvar = 0.0
        self.rto = self.min_rto
        self.samples = 0
        self.backoffs = 0

    def _clamp(self, x: float) -> float:
        return min(self.max_rto, max(self.min_rto, x))

    def sample(self, rtt: float) -> None:
        """An acknowledgement of a batch sent once came ``rtt`` s after its send."""
        if not (math.isfinite(rtt) and rtt >= 0.0):
            return  # a clock step or a bad measurement: no sample
        if self.srtt is None:
            self.srtt, self.rttvar = rtt, rtt / 2.0
        else:
            self.rttvar = (1.0 - BETA) * self.rttvar + BETA * abs(self.srtt - rtt)
            self.srtt = (1.0 - ALPHA) * self.srtt + ALPHA * rtt
        self.rto = self._clamp(self.srtt + K * self.rttvar)
        self.samples += 1

    def backoff(self) -> None:
        """The timer expired (a resend went out): wait twice as long before the next."""
        self.rto = self._clamp(2.0 * self.rto if self.rto > 0 else self.min_rto)
        self.backoffs += 1
