"""Device addresses as health text and logs may show them: without the credentials they carry."""

from __future__ import annotations

from urllib.parse import urlsplit, urlunsplit

#: Query parameters some cameras take credentials in (`?user=..&pwd=..`): their values are redacted.
SECRET_QUERY_KEYS = frozenset({"password", "passwd", "pass", "pwd", "token", "key", "secret", "auth"})


def redacted(url: str) -> str:
    """`url` fit for health text and logs: a password in its user info and the values of credential-like
    query parameters replaced by `***` (a camera's URL often carries its login).

    >>> redacted("rtsp://admin:hunter2@10.0.0.5:554/live?channel=1&pwd=x")
    'rtsp://admin:***@10.0.0.5:554/live?channel=1&pwd=***'
    """
    try:
        split = urlsplit(url)
    except ValueError:
        return "<unparsable URL>"
    netloc = split.netloc
    if split.password is not None:
        user, _, host = netloc.rpartition("@")
        netloc = f"{user.partition(':')[0]}:***@{host}"
    query = "&".join(
        f"{k}=***" if k.lower() in SECRET_QUERY_KEYS else (f"{k}={v}" if sep else k)
        for k, sep, v in (part.partition("=") for part in split.query.split("&") if part)
    )
    return urlunsplit(split._replace(netloc=netloc, query=query))
