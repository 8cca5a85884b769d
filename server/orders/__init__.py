"""Production orders: N good parts of one workpiece, run by the cell one after another.

- `model`: the order and its parts, and the counting (pure: a part's verdict
  from its run's end, what follows a part: go on, complete, or stop at the
  defect limit);
- `book`: the running order book (`OrderBook`): creates, closes, holds and
  resumes orders, hears each run's end, starts the next part, keeps it all in
  the journal (`orders`, `order_parts`);
- `report`: an order's report as rows (JSON and CSV).

What an order does to the cell it does through the cell's own command path
(`Cell.command`) and fault path (an ORDER_DEFECT_LIMIT fault), so the state
machine stays the only code that changes the cell's state.
"""
