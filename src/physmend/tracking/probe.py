"""A database store probed once within a hard deadline, whatever its SQLAlchemy driver.

A server that accepts the TCP connection and never answers (a firewall's tarpit, a stopped process
whose socket the kernel still accepts, the wrong port) would hold a connection attempt for minutes
or forever: some drivers have no connect timeout, others time out only the TCP connect and then wait
on the handshake without limit. So the connection is made in a daemon thread and waited for at most
``timeout`` seconds; the driver is also given its own timeouts, a little longer, where it has them,
so that the thread ends by itself soon after. The driver module is imported before the clock starts:
a missing driver is reported at once (:class:`ModuleNotFoundError`), never as a timeout. No physmend
imports: :mod:`physmend.tracking.store` turns what is raised here into one line naming the store.
"""

from __future__ import annotations

import threading

#: database URI schemes (SQLAlchemy dialects MLflow stores runs in)
DATABASES = ("sqlite", "postgresql", "mysql", "mssql")

#: seconds the driver's own timeouts run past the deadline (they only end the abandoned thread)
DRIVER_SLACK = 2

#: each DBAPI driver's connect keywords that bound a connection attempt, by SQLAlchemy driver name
#: (``dialect+driver://``); a driver not listed gets none and is bounded by the deadline alone
_DRIVER_TIMEOUTS: dict[str, tuple[str, ...]] = {
    "psycopg2": ("connect_timeout",),
    "psycopg": ("connect_timeout",),
    "pg8000": ("timeout",),
    "mysqldb": ("connect_timeout", "read_timeout"),
    "pymysql": ("connect_timeout", "read_timeout"),  # PyMySQL waits for the greeting with read_timeout
    "mysqlconnector": ("connection_timeout",),
    "pyodbc": ("timeout",),  # the ODBC login timeout
    "pymssql": ("login_timeout", "timeout"),
}

#: what to install for a driver module SQLAlchemy could not import (its ``ModuleNotFoundError.name``)
DRIVER_PACKAGES: dict[str, str] = {
    "psycopg": "pip install 'psycopg[binary]', or pip install 'physmend[postgres]' and write postgresql+psycopg2://…",
    "psycopg2": "pip install 'physmend[postgres]'",
    "pg8000": "pip install pg8000",
    "MySQLdb": "pip install mysqlclient, or pip install PyMySQL and write mysql+pymysql://…",
    "pymysql": "pip install PyMySQL",
    "mysql": "pip install mysql-connector-python",
    "pyodbc": "pip install pyodbc (and an ODBC driver for SQL Server), or pip install pymssql and write mssql+pymssql://…",
    "pymssql": "pip install pymssql",
}


class StoreTimeout(Exception):
    """The database did not answer within the deadline (the message says how long was waited)."""


def scheme_of(uri: str) -> str:
    """The dialect of a database URI (``postgresql+psycopg2://…`` -> ``postgresql``), lower case."""
    return uri.split(":", 1)[0].split("+", 1)[0].lower()


def driver_timeouts(driver: str, seconds: int) -> dict[str, int]:
    """The connect keywords bounding ``driver``'s connection attempt to ``seconds``."""
    return {key: int(seconds) for key in _DRIVER_TIMEOUTS.get(driver, ())}


def probe_database(uri: str, timeout: float) -> None:
    """Connect once to the database store ``uri`` and list its tables, within ``timeout`` seconds.

    Stores that are no database (a tracking server, a folder) are not probed.

    Raises:
        StoreTimeout: no answer within ``timeout`` seconds (the attempt is abandoned to its thread).
        ModuleNotFoundError: the driver of the URI's dialect is not installed.
        Exception: whatever SQLAlchemy or the driver raised (a corrupt file, a refused login …).
    """
    if scheme_of(uri) not in DATABASES:
        return
    import sqlalchemy

    url = sqlalchemy.engine.make_url(uri)
    connect_args = driver_timeouts(url.get_driver_name(), int(timeout) + DRIVER_SLACK)
    engine = sqlalchemy.create_engine(url, connect_args=connect_args)  # imports the driver: fails at once
    failure: list[BaseException] = []

    def attempt() -> None:
        try:
            sqlalchemy.inspect(engine).get_table_names()
        except BaseException as exc:  # noqa: BLE001 - handed to the waiting thread
            failure.append(exc)
        finally:
            engine.dispose()

    worker = threading.Thread(target=attempt, name="physmend-store-probe", daemon=True)
    worker.start()
    worker.join(timeout)
    if worker.is_alive():
        raise StoreTimeout(f"no answer within {_seconds(timeout)} s: something accepts connections there but does not "
                           "reply as a database would (check the host, the port and that the database is up)")
    if failure:
        raise failure[0]


def _seconds(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"
