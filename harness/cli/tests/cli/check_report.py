#!/usr/bin/env python3
"""Open a report.html in headless Chromium (Selenium, the system chromedriver) and use it as a person would:
the page loads without a script error; every case is shown; unticking PASS hides every PASS case and no
other; the search box keeps only the cases whose summary holds the text; "expand all" opens them. A
screenshot of the page is written. Exit 0 with "OK ..." on success, 1 with the reason otherwise, 77 when no
browser can be started (the caller decides whether that is a skip).

    check_report.py REPORT_HTML SCREENSHOT_PNG SEARCH_TEXT
"""

import pathlib
import sys


def main():
    html, png, needle = pathlib.Path(sys.argv[1]).resolve(), sys.argv[2], sys.argv[3]
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
        from selenium.webdriver.common.by import By

        opts = webdriver.ChromeOptions()
        opts.binary_location = "/usr/bin/chromium"
        for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1280,1000"):
            opts.add_argument(a)
        opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
        driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    except Exception as e:  # no selenium, no chromium, no driver: not this script's verdict
        print(f"no browser: {e}")
        return 77
    try:
        driver.set_page_load_timeout(30)
        driver.get(html.as_uri())
        errors = [m for m in driver.get_log("browser") if m.get("level") == "SEVERE"]
        if errors:
            return fail(f"script errors on load: {errors}")

        def visible(cls=""):
            return [d for d in driver.find_elements(By.CSS_SELECTOR, f"details.case{cls}") if d.is_displayed()]

        cases = driver.find_elements(By.CSS_SELECTOR, "details.case")
        passes = driver.find_elements(By.CSS_SELECTOR, "details.case.v-PASS")
        fails = driver.find_elements(By.CSS_SELECTOR, "details.case.v-FAIL")
        if not passes or not fails:
            return fail(f"the report needs PASS and FAIL cases: {len(passes)} PASS, {len(fails)} FAIL")
        if len(visible()) != len(cases):
            return fail(f"{len(visible())} of {len(cases)} cases visible before any filter")
        # Failures come first on the page.
        first = cases[0].get_attribute("class")
        if "v-FAIL" not in first:
            return fail(f"the first case is not a FAIL: {first}")

        box = driver.find_element(By.CSS_SELECTOR, '#controls input[data-verdict="PASS"]')
        box.click()
        shown = visible()
        if any("v-PASS" in d.get_attribute("class") for d in shown):
            return fail("a PASS case is still shown with PASS unticked")
        if len(shown) != len(cases) - len(passes):
            return fail(f"{len(shown)} shown with PASS unticked, want {len(cases) - len(passes)}")
        box.click()
        if len(visible()) != len(cases):
            return fail("ticking PASS again does not show every case")

        search = driver.find_element(By.ID, "search")
        search.send_keys(needle)
        shown = visible()
        want = [d for d in cases if needle.lower() in d.find_element(By.TAG_NAME, "summary").get_attribute("textContent").lower()]
        if not want or len(shown) != len(want):
            return fail(f"search {needle!r}: {len(shown)} shown, {len(want)} match")
        if any(needle.lower() not in d.find_element(By.TAG_NAME, "summary").text.lower() for d in shown):
            return fail(f"search {needle!r}: a shown case does not match")
        search.clear()
        search.send_keys(" ")  # an input event with a query that matches nothing but spaces
        search.clear()
        driver.execute_script("document.getElementById('search').dispatchEvent(new Event('input'))")
        if len(visible()) != len(cases):
            return fail("clearing the search does not show every case")

        driver.find_element(By.ID, "expand").click()
        closed = [d for d in cases if d.get_attribute("open") is None]
        if closed:
            return fail(f"{len(closed)} case(s) still closed after expand all")
        driver.find_element(By.ID, "collapse").click()

        box.click()  # the screenshot shows the filtered view
        if not driver.save_screenshot(png):
            return fail("no screenshot")
        size = pathlib.Path(png).stat().st_size
        print(f"OK {len(cases)} cases ({len(fails)} FAIL, {len(passes)} PASS), search {needle!r} kept {len(want)}, screenshot {size} bytes")
        return 0
    finally:
        driver.quit()


def fail(why):
    print(f"FAILED: {why}")
    return 1


if __name__ == "__main__":
    sys.exit(main())
