"""Where the server keeps things: the database (db), the data folder and its rows
(store), audit entries committed after the response (appender), and the caches that
answer viewers from memory (caches)."""
