"""Episodes: running them and their metric tables (:mod:`.runner`, what ``overtake-drive``,
``overtake-train`` and ``overtake-eval`` share), keeping them as records that play again bit for
bit (:mod:`.records`), recording them into Rerun as they are driven (:mod:`.recording`), and
``overtake-drive`` (:mod:`.drive`)."""
