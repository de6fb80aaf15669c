"""``egosurg report CASE``: one self-contained HTML file a review team reads offline or prints
(docs/report.md). It gathers what the other review commands made for the case and draws the
rest: the case's facts and its session's health (``facts.py``), the sterile-field and
line-of-sight outputs (``reviews.py``), each role's view beside the nearest real camera with
its observed share (``views.py``), the timeline (``timeline.py``) and the page itself
(``page.py``). Every picture is embedded (``data:`` URIs), so the file makes no request."""
