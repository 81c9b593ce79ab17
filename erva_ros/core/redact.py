"""Secrets out of what is shown or recorded: a database URI without its password."""

import re
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

#: Query keys of a libpq URI that carry a secret: never shown.
SECRET_KEYS = frozenset({'password', 'sslpassword'})


def redact(uri: str) -> str:
    """Return the URI ``uri`` without its password and secret query keys."""
    try:
        parts = urlsplit(uri)
    except ValueError:
        return uri.split('://', 1)[0] + '://(unparsable URI)'
    netloc = parts.netloc
    if '@' in netloc:
        user, host = netloc.rsplit('@', 1)
        netloc = f'{user.split(":", 1)[0]}@{host}'
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True)
             if k.lower() not in SECRET_KEYS]
    return urlunsplit((parts.scheme, netloc, parts.path, urlencode(query, safe='/'), ''))


def redact_text(text: str) -> str:
    """Return ``text`` with every PostgreSQL URI in it redacted (a command line, a message)."""
    return re.sub(r'postgres(?:ql)?://\S+', lambda m: redact(m.group(0)), text)
